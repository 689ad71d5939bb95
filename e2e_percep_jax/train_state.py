"""What a training run trains and saves: the objective, the optimizer, the train state and its init.

Shared by :mod:`~e2e_percep_jax.train` (which steps the state) and :mod:`~e2e_percep_jax.checkpoint`
(which restores it, and so needs its structure).
"""

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import optax

from e2e_percep_jax import loss as loss_lib
from e2e_percep_jax import model as model_lib
from e2e_percep_jax.config import Config

MODEL_STREAM = 2**32 - 1  # fold_in data for the model's keys; data uses fold_in(root, step), step < this


class Objective(NamedTuple):
    """What is trained: ``init_params(key, cfg) -> params`` and ``loss_fn(params, batch, key, cfg) ->
    (total, metrics)`` (metrics hold ``total``). Hashable (module-level functions), so a train step is
    compiled once per objective; the baselines plug their own in."""

    init_params: Callable
    loss_fn: Callable


PERCEPTION = Objective(model_lib.init_params, loss_lib.loss_fn)  # the paper's model


class TrainState(flax.struct.PyTreeNode):
    """Everything a checkpoint holds.

    step: int32 [], batches consumed (skipped non-finite ones included); params, opt_state: pytrees;
    nonfinite_in_a_row / nonfinite_total: int32 [], skipped updates. Once ``nonfinite_in_a_row``
    reaches ``max_nonfinite_in_a_row`` it stays there and no further update is applied.
    """

    step: jax.Array
    params: Any
    opt_state: Any
    nonfinite_in_a_row: jax.Array
    nonfinite_total: jax.Array


class CarriedTrainState(TrainState):
    """The train state of a ``--data.carry_state`` run: also, per drive slot of the stream (K =
    ``batches_per_drive``), where its drive's last segment left the latent filter: carry = {z1 [K, B,
    z1_dim], z2 [K, B, z2_dim] (the last frame's samples), action [K, B, 2] (from that frame to the
    next segment's first), and with the bird-eye latent grid [K, B, G, G, C], on its lattice grid_offset
    [K, B, 2], with a carried flow grid_flow and grid_lidar (model.FilterState)}. Saved with the rest, so a
    resumed run continues its chains exactly."""

    carry: Any


def _empty_carry(cfg: Config) -> dict:
    """Every drive slot's carry before its drive's first segment: the filter state's latents (the fields that
    ``model.init_filter_state`` fills) and the action, all zeros, for K = ``batches_per_drive`` slots."""
    k, b = cfg.data.batches_per_drive, cfg.data.batch_size
    state = model_lib.init_filter_state(b, cfg)
    carry = {f.name: getattr(state, f.name) for f in dataclasses.fields(state) if f.name not in ("first", "pose")}
    carry = {name: x for name, x in carry.items() if x is not None} | {"action": jnp.zeros((b, 2))}
    return jax.tree.map(lambda x: jnp.zeros((k,) + x.shape, x.dtype), carry)


def learning_rate(cfg: Config) -> optax.ScalarOrSchedule:
    """``--train.learning_rate``, constant; with ``--train.lr_decay_share`` > 0 a schedule of the update's
    count: constant until that share of ``--train.num_steps`` is left, then a cosine down to zero."""
    lr = cfg.train.learning_rate
    if not cfg.train.lr_decay_share:
        return lr  # a constant keeps the optimizer state of runs trained before the schedule existed
    start = decay_start(cfg)
    return optax.join_schedules(
        [optax.constant_schedule(lr), optax.cosine_decay_schedule(lr, cfg.train.num_steps - start)], [start]
    )


def decay_start(cfg: Config) -> int:
    """The update from which the rate decays (``num_steps`` where it stays constant)."""
    if not cfg.train.lr_decay_share:
        return cfg.train.num_steps
    return cfg.train.num_steps - max(1, round(cfg.train.lr_decay_share * cfg.train.num_steps))


def learning_rate_at(cfg: Config, step: int) -> float:
    """The learning rate at update ``step`` (from 0; skipped non-finite updates do not count), for the logs."""
    lr = learning_rate(cfg)
    return float(lr(step)) if callable(lr) else lr


def optimizer(cfg: Config) -> optax.GradientTransformation:
    """Adam at :func:`learning_rate`, after a global-norm clip if ``--train.max_grad_norm`` > 0 (plain Adam
    otherwise, so a run trained without clipping keeps its optimizer state's structure)."""
    adam = optax.adam(learning_rate(cfg))
    clip = cfg.train.max_grad_norm
    return optax.chain(optax.clip_by_global_norm(clip), adam) if clip else adam


def model_keys(seed: int) -> tuple[jax.Array, jax.Array]:
    """(init key, noise root) of a run; step s's latent noise is ``fold_in(noise_root, s)``."""
    init_key, noise_root = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(seed), MODEL_STREAM))
    return init_key, noise_root


def init_state(cfg: Config, objective: Objective = PERCEPTION) -> TrainState:
    params = objective.init_params(model_keys(cfg.train.seed)[0], cfg)
    zero = lambda: jnp.zeros((), jnp.int32)  # distinct buffers: the state is donated to the step
    fields = dict(
        step=zero(),
        params=params,
        opt_state=optimizer(cfg).init(params),
        nonfinite_in_a_row=zero(),
        nonfinite_total=zero(),
    )
    return CarriedTrainState(**fields, carry=_empty_carry(cfg)) if cfg.data.carry_state else TrainState(**fields)
