"""A training run's orbax checkpoints ``<workdir>/checkpoints/<step>``: the manager that writes them, their
listing, the one reader, the resume from the newest intact one, whether a config continues the run, and
the params restored for inference (no evaluation code, no cv2)."""

import dataclasses
import os
import sys

import jax
import orbax.checkpoint as ocp

from e2e_percep_jax import config as config_lib
from e2e_percep_jax.config import Config, MissingRunFileError, run_config
from e2e_percep_jax.train_state import PERCEPTION, Objective, TrainState, init_state

MAX_CHECKPOINTS_KEPT = 3
# Fields that may change when a run resumes; anything else would make the checkpoint a different run.
RESUMABLE_CHANGES = ("train.num_steps", "train.log_every", "train.checkpoint_every", "train.max_nonfinite_in_a_row")


class NoIntactCheckpointError(RuntimeError):
    """Every checkpoint of the run being resumed failed to restore (all are left as they were)."""


def manager(workdir: str, remove_temporary: bool = True) -> ocp.CheckpointManager:
    """The manager of run ``workdir``'s checkpoints (keeps the newest ``MAX_CHECKPOINTS_KEPT``).

    ``remove_temporary`` deletes a killed save's temporary folders in a background thread that ``close``
    does not wait for (orbax 0.12): a process that exits at once, as on a config error after
    :func:`check_resumable`, would log that thread's failure at interpreter shutdown. Only the training
    manager, whose first save waits for it, removes them."""
    return ocp.CheckpointManager(
        os.path.join(os.path.abspath(workdir), "checkpoints"),
        options=ocp.CheckpointManagerOptions(
            max_to_keep=MAX_CHECKPOINTS_KEPT, cleanup_tmp_directories=remove_temporary
        ),
    )


def _restore_failure(error: Exception) -> str:
    """One line for why orbax could not restore a checkpoint (it raises many types, some with pages of text):
    the first line of the innermost cause (a read error wrapped in orbax's own has the file and the reason)."""
    while error.__cause__ is not None:
        error = error.__cause__
    text = str(error).strip()
    return f"{type(error).__name__}: {text.splitlines()[0][:300] if text else ''}"


def saved_steps(workdir: str) -> list[int]:
    """The steps of the finished checkpoints ``checkpoints/<step>`` of run ``workdir``, oldest first (orbax
    writes a checkpoint under a temporary name and renames it when done; a resume sets a damaged one aside as
    ``<step>.damaged``)."""
    path = os.path.join(workdir, "checkpoints")
    names = os.listdir(path) if os.path.isdir(path) else []
    return sorted(int(d) for d in names if d.isascii() and d.isdigit())


def read_checkpoint(workdir: str, step: int, abstract):
    """Train state ``step`` (one of :func:`saved_steps`) of run ``workdir``, restored into ``abstract`` (shapes,
    dtypes, shardings): the one reader of a checkpoint, for resuming and for :func:`restore_params`.
    Raises ValueError, one line naming the checkpoint, if it cannot be read into that structure (damaged,
    or written by another config)."""
    path = os.path.join(os.path.abspath(workdir), "checkpoints", str(step))
    try:
        # The one item the training manager saves, read without a manager: a manager reads every step's
        # metadata when it starts (logging about each damaged one), and fixes its item layout at its first
        # restore from that step's folder, so a damaged step without the item would fail the older ones too.
        with ocp.StandardCheckpointer() as checkpointer:
            return checkpointer.restore(os.path.join(path, ocp.checkpoint_manager.DEFAULT_ITEM_NAME), abstract)
    except Exception as e:  # orbax raises many types (decode, data loss, tree or shape mismatch): one line
        raise ValueError(
            f"{path}: cannot be restored for its config.json (damaged, or written by another "
            f"config): {_restore_failure(e)}"
        ) from None


def restore_newest_intact(checkpoints: ocp.CheckpointManager, state: TrainState, workdir: str) -> tuple:
    """(state, step) of the newest checkpoint of ``checkpoints`` (run ``workdir``'s manager) that restores
    into ``state``'s structure and shardings. The newer ones that did not restore are then renamed
    ``<step>.damaged`` (kept, and out of the manager's way), one line on stderr each. When none restores,
    raises :class:`NoIntactCheckpointError` and renames nothing: the checkpoints may be intact and
    ``config.json`` the odd one out."""
    abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding), state)
    failed = []
    for step in reversed(saved_steps(workdir)):
        try:
            restored = read_checkpoint(workdir, step, abstract)
        except ValueError as e:
            failed.append((os.path.join(workdir, "checkpoints", str(step)), str(e)))
            continue
        for path, why in failed:
            if jax.process_index() == 0:
                os.rename(path, path + ".damaged")
            print(f"checkpoint {why}; kept as {path}.damaged", file=sys.stderr, flush=True)
        checkpoints.reload()
        return restored, step
    raise NoIntactCheckpointError(
        f"no checkpoint in {workdir}/checkpoints restores, nothing was changed; the newest: "
        f"{failed[0][1] if failed else 'none'}"
    )


def restore_params(workdir: str, cfg: Config | None = None, step: int | None = None, objective: Objective = PERCEPTION):
    """(cfg, params, step) of the run in ``workdir``: its config.json (unless ``cfg`` is given) and the
    params of checkpoint ``step`` (default: the latest), restored with the same abstract train state
    that ``train.train`` saves for ``objective`` (default: the perception model). Raises
    MissingRunFileError (a ValueError) if there is no checkpoint, ValueError (one line, naming the
    checkpoint) if ``step`` is not saved or cannot be restored; writes nothing."""
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
    return cfg, read_checkpoint(workdir, step, abstract).params, step


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
            f"--{name}={value} differs from the run being resumed in {workdir} ({old.get(name)}); "
            f"pass --{name}={config_lib.flag_value(old.get(name))} to resume it, or use a new --workdir"
        )
    return latest
