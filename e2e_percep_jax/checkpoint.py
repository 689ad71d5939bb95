"""A training run's orbax checkpoints ``<workdir>/checkpoints/<step>``: the manager that writes them, their
listing, the one reader, the resume from the newest intact one, whether a config continues the run, and
the params restored for inference (no evaluation code, no cv2)."""

import dataclasses
import logging
import os
import sys

import jax
import numpy as np
import orbax.checkpoint as ocp
from etils import epath

from e2e_percep_jax import config as config_lib
from e2e_percep_jax.config import Config, MissingRunFileError, run_config
from e2e_percep_jax.train_state import PERCEPTION, Objective, TrainState, decay_start, init_state

MAX_CHECKPOINTS_KEPT = 3
# Fields that may change when a run resumes; anything else would make the checkpoint a different run.
RESUMABLE_CHANGES = ("train.num_steps", "train.log_every", "train.checkpoint_every", "train.max_nonfinite_in_a_row")
# Why a checkpoint does not restore, as its one line says (orbax's own text goes to the debug log).
DAMAGED, OTHER_NETWORK = "damaged", "holds another network"
# What to do about a checkpoint of another network (the config.json or the checkpoint is the odd one out).
USE_ITS_CONFIG = "use its training config"
logger = logging.getLogger(__name__)


class NoIntactCheckpointError(RuntimeError):
    """Every checkpoint of the run being resumed failed to restore (all are left as they were)."""


class UnreadableCheckpointError(ValueError):
    """Checkpoint ``path`` does not restore into the structure asked for; ``why``: :data:`DAMAGED` or
    :data:`OTHER_NETWORK`."""

    def __init__(self, path: str, why: str):
        super().__init__(f"{path}: cannot be restored ({why})")
        self.path, self.why = path, why


def manager(workdir: str, remove_temporary: bool = True) -> ocp.CheckpointManager:
    """The manager of run ``workdir``'s checkpoints (keeps the newest ``MAX_CHECKPOINTS_KEPT``).

    ``remove_temporary`` deletes a killed save's temporary folders in a background thread that ``close``
    does not wait for (orbax 0.12): a process that exits at once, as on a config error after
    :func:`check_resumable`, would log that thread's failure at interpreter shutdown. Only the training
    manager, whose first save waits for it, removes them.

    It starts without reading each step's metadata (times and metrics, unused here): orbax would log a
    warning or error for each damaged step, which the resume reports in its own line; its ``reload`` reads
    them, after the resume has set the damaged ones aside."""
    return ocp.CheckpointManager(
        os.path.join(os.path.abspath(workdir), "checkpoints"),
        options=ocp.CheckpointManagerOptions(
            max_to_keep=MAX_CHECKPOINTS_KEPT, cleanup_tmp_directories=remove_temporary, lightweight_initialize=True
        ),
    )


def _arrays(tree) -> dict:
    """{path: (shape, dtype)} of a tree of arrays or array metadata, the path's keys by name or index alone (the
    saved metadata keeps a train state's attributes and tuple items as dict keys)."""
    return {
        jax.tree_util.keystr(path, simple=True, separator="/"): (tuple(x.shape), np.dtype(x.dtype))
        for path, x in jax.tree_util.tree_flatten_with_path(tree)[0]
    }


def _why_unreadable(item: str, abstract) -> str:
    """:data:`OTHER_NETWORK` if the checkpoint item ``item`` lists its arrays (its metadata reads) and they differ
    from ``abstract``'s in name, shape or dtype; else :data:`DAMAGED`."""
    # The handler, not a Checkpointer: that one logs a warning for each missing or unreadable metadata file.
    handler = ocp.StandardCheckpointHandler()
    try:
        saved = _arrays(handler.metadata(epath.Path(item)))
    except Exception:  # metadata that does not read is damage too
        logger.debug("%s: its metadata does not read", item, exc_info=True)
        return DAMAGED
    finally:
        handler.close()
    return OTHER_NETWORK if saved and saved != _arrays(abstract) else DAMAGED


def _set_aside(path: str) -> str:
    """Renames checkpoint ``path`` to the first free name of ``<step>.damaged``, ``<step>.damaged.2``, ...
    (one set aside by an earlier resume keeps its name) and returns that name."""
    name, n = f"{os.path.basename(path)}.damaged", 1
    while os.path.lexists(os.path.join(os.path.dirname(path), name)):
        n += 1
        name = f"{os.path.basename(path)}.damaged.{n}"
    os.rename(path, os.path.join(os.path.dirname(path), name))
    return name


def saved_steps(workdir: str) -> list[int]:
    """The steps of the finished checkpoints ``checkpoints/<step>`` of run ``workdir``, oldest first (orbax
    writes a checkpoint under a temporary name and renames it when done; a resume sets a damaged one aside as
    ``<step>.damaged`` or ``<step>.damaged.<n>``)."""
    path = os.path.join(workdir, "checkpoints")
    names = os.listdir(path) if os.path.isdir(path) else []
    return sorted(int(d) for d in names if d.isascii() and d.isdigit())


def read_checkpoint(workdir: str, step: int, abstract):
    """Train state ``step`` (one of :func:`saved_steps`) of run ``workdir``, restored into ``abstract`` (shapes,
    dtypes, shardings): the one reader of a checkpoint, for resuming and for :func:`restore_params`.
    Raises :class:`UnreadableCheckpointError` if it cannot be read into that structure, and logs orbax's
    error at DEBUG level (a launcher's ``--verbosity=1`` shows it)."""
    path = os.path.join(os.path.abspath(workdir), "checkpoints", str(step))
    # The one item the training manager saves, read without a manager: a manager fixes its item layout at
    # its first restore from that step's folder, so a damaged step without the item would fail the older ones.
    item = os.path.join(path, ocp.checkpoint_manager.DEFAULT_ITEM_NAME)
    try:
        with ocp.StandardCheckpointer() as checkpointer:
            return checkpointer.restore(item, abstract)
    except Exception:  # orbax raises many types (decode, data loss, tree or shape mismatch), some pages long
        logger.debug("%s: orbax could not restore it", path, exc_info=True)
        config_lib.quieten_abandoned_reads(item + os.sep)
        why = _why_unreadable(item, abstract)
    raise UnreadableCheckpointError(path, why)


def restore_newest_intact(checkpoints: ocp.CheckpointManager, state: TrainState, workdir: str) -> tuple:
    """(state, step) of the newest checkpoint of ``checkpoints`` (run ``workdir``'s manager) that restores
    into ``state``'s structure and shardings. The newer ones that did not restore are then set aside as
    ``<step>.damaged``, or ``<step>.damaged.<n>`` with the first free n >= 2 when an earlier resume took that
    name (kept, and out of the manager's way), by process 0, which says so in one line on stderr each. When
    none restores, raises :class:`NoIntactCheckpointError` and renames nothing: the checkpoints may be
    intact and ``config.json`` the odd one out."""
    abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding), state)
    failed = []
    for step in reversed(saved_steps(workdir)):
        try:
            restored = read_checkpoint(workdir, step, abstract)
        except UnreadableCheckpointError as e:
            failed.append(e)
            continue
        for e in failed:
            if jax.process_index() == 0:  # the one that renames knows the name it took
                kept = _set_aside(e.path)
                print(f"checkpoint {e}; kept as {kept}, resumed from step {step}", file=sys.stderr, flush=True)
        checkpoints.reload()
        return restored, step
    why = f"newest, {os.path.basename(failed[0].path)}: {failed[0].why}" if failed else "none saved"
    todo = USE_ITS_CONFIG if failed and failed[0].why == OTHER_NETWORK else "retrain in a new --workdir"
    raise NoIntactCheckpointError(
        f"{os.path.abspath(workdir)}/checkpoints: no step restores ({why}); stopped, all kept: {todo}"
    )


def restore_params(workdir: str, cfg: Config | None = None, step: int | None = None, objective: Objective = PERCEPTION):
    """(cfg, params, step) of the run in ``workdir``: its config.json (unless ``cfg`` is given) and the
    params of checkpoint ``step`` (default: the latest), restored with the same abstract train state
    that ``train.train`` saves for ``objective`` (default: the perception model). Raises
    MissingRunFileError (a ValueError) if there is no checkpoint, ValueError (one line, naming the
    checkpoint, why and what to do) if ``step`` is not saved or cannot be restored; writes nothing."""
    workdir = os.path.abspath(workdir)
    cfg = run_config(workdir) if cfg is None else cfg
    saved = saved_steps(workdir)
    if not saved:
        raise MissingRunFileError(f"no checkpoint in {workdir}/checkpoints")
    if step is not None and step not in saved:
        raise ValueError(f"--step={step}: {workdir} has checkpoints at steps {saved}")
    step = saved[-1] if step is None else step
    sharding = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    abstract = jax.tree.map(
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding),
        jax.eval_shape(lambda: init_state(cfg, objective)),
    )
    try:
        return cfg, read_checkpoint(workdir, step, abstract).params, step
    except UnreadableCheckpointError as e:
        older = ", ".join(str(s) for s in saved if s < step)
        todo = USE_ITS_CONFIG if e.why == OTHER_NETWORK else f"use an older step ({older})" if older else "retrain"
        raise ValueError(f"{e}; stopped, nothing changed: {todo}") from None


def _flat_config(cfg: Config) -> dict:
    return {f"{s}.{k}": v for s, fields in dataclasses.asdict(cfg).items() for k, v in fields.items()}


def check_resumable(cfg: Config, workdir: str) -> int | None:
    """The latest checkpoint's step of run ``workdir`` (None: none, a fresh run), after checking that ``cfg``
    continues that run: raises ValueError naming the first flag that differs from its config.json.
    Compiles nothing."""
    with manager(workdir, remove_temporary=False) as checkpoints:
        latest = checkpoints.latest_step()
    if latest is None:
        return None
    old = _flat_config(run_config(workdir))  # a field added since takes its default
    for name, value in _flat_config(cfg).items():
        if name.startswith("eval.") or name in RESUMABLE_CHANGES or old.get(name) == value:
            continue
        raise ValueError(
            f"--{name}={config_lib.flag_value(value)} differs from the run being resumed in {workdir}; "
            f"pass --{name}={config_lib.flag_value(old.get(name))} to resume it, or use a new --workdir"
        )
    # A decaying rate is a schedule over num_steps: a new count moves where the decay starts, which the
    # steps already trained cannot follow once either start lies behind them.
    trained = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, num_steps=old["train.num_steps"]))
    if cfg.train.num_steps != trained.train.num_steps and latest > min(decay_start(cfg), decay_start(trained)):
        raise ValueError(
            f"--train.num_steps={cfg.train.num_steps}: {workdir} reached step {latest}, and its rate decays from "
            f"step {decay_start(trained)}; pass --train.num_steps={trained.train.num_steps} or use a new --workdir"
        )
    return latest
