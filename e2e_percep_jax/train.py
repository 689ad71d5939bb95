"""Training: Adam on :func:`~e2e_percep_jax.loss.loss_fn`, data-parallel, checkpointed, resumable.

What is trained is an :class:`Objective` (params init and loss), the perception model by default; the
single-frame baselines (``baselines.py``) plug in their own and keep everything else.

Randomness, all from ``cfg.train.seed``: the batch of step s is a function of (seed, s) alone
(``batch.batch_stream``): with ``batches_per_drive`` K = 1 it is ``make_batch(batch_key(seed, s))``,
``batch_key = fold_in(PRNGKey(seed), s)``; with the presets' K > 1 a segment of drive
``batch_key(seed, g)``. The model's root is ``fold_in(PRNGKey(seed), 2**32 - 1)`` (a step or drive the
data stream never reaches), split into the init key and the noise root, and step s samples its
latents with ``fold_in(noise_root, s)``. So a run is a function of (config, step) only, and a run
killed and resumed from a checkpoint reproduces the uninterrupted run exactly.

Data parallel: one 1-D mesh ``("data",)`` over all devices (of all processes); batches are sharded
along B, the train state is replicated; ``jit`` inserts the gradient all-reduce. With several processes,
SIGTERM / SIGINT caught by any of them stops all after the same step.

Carried state (``--data.carry_state``, the learned pose route): the train state also holds, per drive
slot of the stream, where the latent filter left that drive's last segment, and step s's batch continues
from it (:class:`CarriedTrainState`): truncated backpropagation through time over a drive's K segments.

Outputs in ``workdir``: ``config.json`` (the resolved config), ``motion_model.json`` (the belief pose
head's calibrated motion model, :func:`ensure_motion_model`), ``metrics.jsonl`` (one record per
``log_every`` steps: mean of each loss term over those steps, gradient norm, steps/s, non-finite
counters), ``checkpoints/<step>`` (orbax; every ``checkpoint_every`` steps and at exit), and with
tensorboardX installed TensorBoard event files of the same records and of reconstructions and the pose
belief at every checkpoint (:mod:`e2e_percep_jax.board`).
"""

import contextlib
import dataclasses
import functools
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from e2e_percep_jax import board as board_lib
from e2e_percep_jax import calibration, checkpoint
from e2e_percep_jax import loss as loss_lib
from e2e_percep_jax import model as model_lib
from e2e_percep_jax.config import Config, TrainConfig, validate
from e2e_percep_jax.launch import eta
from e2e_percep_jax.sim import batch as batch_lib
from e2e_percep_jax.sim import town as town_lib
from e2e_percep_jax.sim import world
from e2e_percep_jax.sim.motion import MotionModel
from e2e_percep_jax.train_state import (
    PERCEPTION,
    CarriedTrainState,
    Objective,
    TrainState,
    init_state,
    learning_rate_at,
    model_keys,
    optimizer,
)

Batches = Callable[[int], Iterator[tuple[int, dict]]]  # start_step -> (step, batch) from start_step on


class NonFiniteLossError(RuntimeError):
    """Training stopped after ``max_nonfinite_in_a_row`` consecutive non-finite losses."""


class TrainingInterrupted(Exception):
    """SIGTERM / SIGINT arrived; a checkpoint of the last completed step was written."""

    def __init__(self, signum: int, step: int):
        super().__init__(
            f"interrupted by {signal.Signals(signum).name} at step {step}; checkpoint saved, "
            "rerun the same command to resume"
        )
        self.signum, self.step = signum, step


@contextlib.contextmanager
def exit_on_stop():
    """For launchers: a run stopped by non-finite losses exits with one error line; one stopped by
    SIGINT / SIGTERM (after its checkpoint) exits with status 128 + the signal."""
    try:
        yield
    except (NonFiniteLossError, checkpoint.NoIntactCheckpointError) as e:
        sys.exit(f"error: {e}")
    except TrainingInterrupted as e:
        print(e, file=sys.stderr)
        sys.exit(128 + e.signum)


def _carried_loss(state: CarriedTrainState, batch: dict, key: jax.Array, cfg: Config):
    """(value_and_grad of the perception loss on ``batch`` continuing its drive's chain, the carry after
    it). Batch ``state.step`` is segment (step // K) % K of the drive in slot step % K (batch.drive_slot):
    segment 0 starts fresh; later ones start where the slot's last batch ended. The carry is an input,
    so no gradient crosses a segment boundary."""
    per_drive = cfg.data.batches_per_drive
    slot, segment = state.step % per_drive, (state.step // per_drive) % per_drive
    carried = jax.tree.map(lambda x: x[slot], state.carry)
    first = jnp.full(carried["action"].shape[:1], segment == 0)
    latents = {k: v for k, v in carried.items() if k != "action"}
    start = (model_lib.FilterState(**latents, first=first), carried["action"])
    (total, (metrics, (end, action))), grads = jax.value_and_grad(loss_lib.sequence_loss, has_aux=True)(
        state.params, batch, key, cfg, start
    )
    ended = {k: action if k == "action" else getattr(end, k) for k in state.carry}
    # A non-finite end (a skipped step's) would poison the chain: its rows restart from zeros.
    carry = jax.tree.map(lambda c, e: c.at[slot].set(jnp.where(jnp.isfinite(e), e, 0.0)), state.carry, ended)
    return ((total, metrics), grads), carry


def train_step(
    state: TrainState, batch: dict, key: jax.Array, cfg: Config, objective: Objective = PERCEPTION
) -> tuple[TrainState, dict]:
    """One Adam step of ``objective`` on ``batch`` ([B, T+1, ...] frame contract) with latent noise ``key``.

    A non-finite loss or gradient norm skips the update (params and optimizer state unchanged) and
    counts it. Returns (state, metrics): the loss terms, ``grad_norm`` and the non-finite counters.
    """
    if cfg.data.carry_state:
        ((_, metrics), grads), carry = _carried_loss(state, batch, key, cfg)
        state = state.replace(carry=carry)
    else:
        (_, metrics), grads = jax.value_and_grad(objective.loss_fn, has_aux=True)(state.params, batch, key, cfg)
    grad_norm = optax.tree.norm(grads)
    finite = jnp.isfinite(metrics["total"]) & jnp.isfinite(grad_norm)  # a NaN / inf grad makes the norm so
    halted = state.nonfinite_in_a_row >= cfg.train.max_nonfinite_in_a_row
    apply = finite & ~halted
    updates, opt_state = optimizer(cfg).update(grads, state.opt_state, state.params)
    in_a_row = jnp.where(halted, state.nonfinite_in_a_row, jnp.where(finite, 0, state.nonfinite_in_a_row + 1))
    state = state.replace(
        step=state.step + 1,
        params=optax.tree.where(apply, optax.apply_updates(state.params, updates), state.params),
        opt_state=optax.tree.where(apply, opt_state, state.opt_state),
        nonfinite_in_a_row=in_a_row,
        nonfinite_total=state.nonfinite_total + (~finite).astype(jnp.int32),
    )
    return state, dict(metrics, grad_norm=grad_norm, nonfinite_in_a_row=in_a_row, nonfinite_total=state.nonfinite_total)


def make_mesh(devices=None) -> Mesh:
    """1-D data-parallel mesh ``("data",)`` over ``devices`` (default: every device of every process)."""
    return Mesh(np.asarray(jax.devices() if devices is None else devices), ("data",))


def shard_batch(batch: dict, mesh: Mesh, cfg: Config) -> dict:
    """The fields of a global batch [B, T+1, ...] that the loss reads under ``cfg`` (``loss.batch_keys``),
    sharded along B over ``mesh``.

    With several processes each holds the same global batch (it is a function of the step) and
    contributes the rows of its own devices.
    """
    sharding = NamedSharding(mesh, PartitionSpec("data"))
    batch = {k: batch[k] for k in loss_lib.batch_keys(cfg) if k in batch}
    if jax.process_count() == 1:
        return jax.device_put(batch, sharding)
    host = jax.tree.map(np.asarray, batch)
    return jax.tree.map(lambda x: jax.make_array_from_callback(x.shape, sharding, lambda i: x[i]), host)


# TrainConfig fields the jitted step never reads; any other field (a new one too) stays in its config.
_NOT_READ_BY_STEP = ("seed", "num_steps", "checkpoint_every", "log_every")


def step_config(cfg: Config) -> Config:
    """``cfg`` with every field :func:`train_step` does not read set to its default (the batch's
    shapes come from the batch), so runs that differ only in those share one compilation. A decaying
    learning rate reads ``num_steps`` (where its decay starts)."""
    unread = {name: getattr(TrainConfig(), name) for name in _NOT_READ_BY_STEP}
    if cfg.train.lr_decay_share:
        del unread["num_steps"]
    data = {"image_size": cfg.data.image_size}
    if cfg.data.carry_state:  # the step picks the batch's drive slot and segment
        data.update(carry_state=True, batches_per_drive=cfg.data.batches_per_drive)
    return dataclasses.replace(
        Config(),
        model=cfg.model,
        data=dataclasses.replace(Config().data, **data),
        train=dataclasses.replace(cfg.train, **unread),
    )


def make_train_step(cfg: Config, mesh: Mesh, objective: Objective = PERCEPTION):
    """:func:`train_step` jitted for ``mesh``: state and key replicated, batch sharded along B."""
    return _jitted_train_step(step_config(cfg), mesh, objective)


@functools.cache  # the same jitted object for the same (step config, mesh, objective): compiled once
def _jitted_train_step(cfg: Config, mesh: Mesh, objective: Objective):
    replicated, sharded = NamedSharding(mesh, PartitionSpec()), NamedSharding(mesh, PartitionSpec("data"))
    return jax.jit(
        lambda state, batch, key: train_step(state, batch, key, cfg, objective),
        in_shardings=(replicated, sharded, replicated),
        out_shardings=replicated,
        donate_argnums=0,
    )


def world_batches(cfg: Config) -> Batches:
    """The world's batch stream for ``cfg`` (town built once)."""
    town = town_lib.build_town(cfg.world.town_seed)
    # Batches read only the world and data sections: the rest reset, so runs that differ in training
    # fields share one compilation of the batch.
    world_cfg = Config(world=cfg.world, data=cfg.data)
    return lambda start: batch_lib.batch_stream(town, world_cfg, cfg.train.seed, start_step=start)


def check_run(cfg: Config, workdir: str, objective: Objective = PERCEPTION) -> int | None:
    """Every check that needs no compilation: the config, its fit to the devices, and, if ``workdir``
    holds a checkpoint, that ``cfg`` continues that run. Raises ValueError naming the flag; returns the
    step to resume from (None for a fresh run)."""
    validate(cfg)
    world.check_vehicle_count(cfg.world, cfg.world.town_seed)
    if cfg.data.carry_state and objective is not PERCEPTION:
        raise ValueError("--data.carry_state: only the perception model carries a filter state across segments")
    n_devices = jax.device_count()
    if cfg.data.batch_size % n_devices:
        raise ValueError(
            f"--data.batch_size={cfg.data.batch_size} must be a multiple of the number of devices ({n_devices})"
        )
    if cfg.data.place_frames % n_devices:
        raise ValueError(
            f"--data.place_frames={cfg.data.place_frames} must be a multiple of the number of devices ({n_devices})"
        )
    return checkpoint.check_resumable(cfg, workdir)


def _host(tree):
    """Replicated device arrays -> NumPy (reads this process's copy, so it works on any process)."""
    return jax.tree.map(lambda x: np.asarray(x.addressable_data(0)), tree)


def _truncate_metrics(path: str, last_step: int) -> None:
    """Drops records past ``last_step`` (written by a killed run after its last checkpoint)."""
    if not os.path.exists(path):
        return
    with open(path) as f:
        lines = [line for line in f if line.strip() and json.loads(line)["step"] <= last_step]
    with open(path, "w") as f:
        f.writelines(lines)


class _StopSignals:
    """Turns SIGTERM / SIGINT into a flag checked between steps, so a step is never cut in half."""

    def __init__(self):
        self.signum = None
        self._previous = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGTERM, signal.SIGINT):
                self._previous[s] = signal.signal(s, self._handle)
        return self

    def _handle(self, signum, frame):
        self.signum = signum

    def agreed(self) -> int | None:
        """The signal that stops the run, the same in every process: with several, the largest any of them
        caught (a collective, so every process calls it at the same point). A process stopping alone would
        leave the others waiting for it in the next step's all-reduce."""
        if jax.process_count() == 1:
            return self.signum
        return int(np.max(multihost_utils.process_allgather(np.int32(self.signum or 0)))) or None

    def __exit__(self, *exc):
        for s, handler in self._previous.items():
            signal.signal(s, handler)


def ensure_motion_model(cfg: Config, workdir: str) -> MotionModel:
    """The run's calibrated motion model (``motion_model.json``), fitted on training drives of its world
    (:mod:`e2e_percep_jax.calibration`, about half a minute) unless the run already has one."""
    try:
        return MotionModel.load(workdir)
    except ValueError:
        print("fitting the motion model on training drives", flush=True)
        model = calibration.calibrate(cfg)
        model.save(workdir)
        return model


def train(cfg: Config, workdir: str, batches: Batches | None = None, objective: Objective = PERCEPTION) -> TrainState:
    """Trains ``objective`` (default: the perception model) under ``cfg`` in ``workdir`` up to
    ``cfg.train.num_steps``, resuming from its latest checkpoint.

    ``batches`` (default: :func:`world_batches`) maps a start step to (step, batch) pairs. Every
    configuration error raises ValueError (:func:`check_run`) before anything is compiled. Raises
    :class:`NonFiniteLossError` (no checkpoint written for the bad steps) or
    :class:`TrainingInterrupted` (checkpoint written). Returns the final state.
    """
    start, t = check_run(cfg, workdir, objective), cfg.train
    workdir = os.path.abspath(workdir)
    main_process = jax.process_index() == 0
    config_path, metrics_path = os.path.join(workdir, "config.json"), os.path.join(workdir, "metrics.jsonl")
    manager = checkpoint.manager(workdir)
    mesh = make_mesh()
    state = jax.device_put(init_state(cfg, objective), NamedSharding(mesh, PartitionSpec()))
    if start is not None:
        state, start = checkpoint.restore_newest_intact(manager, state, workdir)
        print(f"resumed from step {start} in {workdir}", flush=True)
    start = start or 0
    if main_process:  # (once the run is known to go on: a resume that stops has changed nothing)
        with open(config_path, "w") as f:
            f.write(cfg.to_json())
        if batches is None and objective is PERCEPTION and cfg.model.pose_head == "belief":
            ensure_motion_model(cfg, workdir)
        _truncate_metrics(metrics_path, start)
    step_fn = make_train_step(cfg, mesh, objective)
    board = board_lib.Board(workdir if main_process else None, start)
    noise_root = model_keys(t.seed)[1]
    stream = (batches or world_batches(cfg))(start)
    compiled, pending, tick = None, [], time.perf_counter()

    def save(step):
        if manager.latest_step() != step:
            manager.save(step, args=ocp.args.StandardSave(state))

    def check_finite(step):
        in_a_row = int(_host(state.nonfinite_in_a_row))
        if in_a_row >= t.max_nonfinite_in_a_row:
            manager.wait_until_finished()
            raise NonFiniteLossError(
                f"stopping at step {step}: {in_a_row} non-finite losses in a row "
                f"(--train.max_nonfinite_in_a_row={t.max_nonfinite_in_a_row}); they updated nothing; "
                f"last checkpoint kept: step {manager.latest_step()}"
            )

    with _StopSignals() as stop, manager:  # closing the manager waits for pending saves
        for step, batch in stream:
            if step >= t.num_steps or stop.agreed() is not None:
                break
            batch = shard_batch(batch, mesh, cfg)
            key = jax.random.fold_in(noise_root, step)
            if compiled is None:  # compiled once, timed, outside the steps/s clock
                compile_start = time.perf_counter()
                compiled = step_fn.lower(state, batch, key).compile()
                print(f"compiled the train step in {time.perf_counter() - compile_start:.1f} s", flush=True)
                tick = time.perf_counter()
            state, metrics = compiled(state, batch, key)
            pending.append(metrics)
            done = step + 1
            if done % t.log_every == 0 or done == t.num_steps:
                records = _host(pending)
                now = time.perf_counter()
                steps_per_s = len(pending) / (now - tick)
                record = {
                    "step": done,
                    **{k: float(np.mean([r[k] for r in records])) for k in records[0]},
                    "nonfinite_in_a_row": int(records[-1]["nonfinite_in_a_row"]),
                    "nonfinite_total": int(records[-1]["nonfinite_total"]),
                    "steps_per_s": steps_per_s,
                }
                board.scalars(record, learning_rate_at(cfg, done))
                if main_process:
                    with open(metrics_path, "a") as f:
                        f.write(json.dumps(record) + "\n")
                    print(
                        f"step {done}/{t.num_steps}  loss {record['total']:.6g}  {steps_per_s:.2f} steps/s  "
                        f"ETA {eta((t.num_steps - done) / steps_per_s)}",
                        flush=True,
                    )
                pending, tick = [], now
                check_finite(done)
            if done % t.checkpoint_every == 0:
                check_finite(done)
                save(done)
                # (single-process runs only: the preview is a computation every process would have to run)
                if board.writer is not None and objective is PERCEPTION and jax.process_count() == 1:
                    board.images(
                        done,
                        jax.device_get(
                            board_lib.preview(
                                state.params, *(batch[k] for k in ("camera", "lidar", "roadmap", "action", "pose")), cfg
                            )
                        ),
                    )
        final_step = int(_host(state.step))
        check_finite(final_step)
        save(final_step)
        board.close()
        signum = stop.agreed()
        if signum is not None:
            raise TrainingInterrupted(signum, final_step)
    return state
