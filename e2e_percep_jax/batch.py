"""Training batches generated on the fly, in one jit: reset B worlds, warm their traffic up, drive and observe.

A batch is the frame contract (DESIGN §2) with leading [B, T+1] axes: camera, lidar, roadmap uint8
[B, T+1, R, R, 3]; det_cls float32 [B, T+1, R, R, 1]; det_reg float32 [B, T+1, R, R, 6]; pose float32
[B, T+1, 5]; action float32 [B, T+1, 2]; boxes float32 [B, T+1, N, 5]; boxes_valid, boxes_occluded bool
[B, T+1, N]. Every sequence starts from a fresh ``world.reset`` with its own key and records after
``cfg.data.warmup_steps`` steps (steady traffic), so a batch depends only on its key and successive
batches are independent. Nothing touches the disk.
"""
import functools

import jax

from e2e_percep_jax import config as config_lib
from e2e_percep_jax import sensors, world


def rollout(state, town, num_frames: int, image_size: int):
    """Drives ``num_frames`` world steps from ``state``, observing before each step.

    Frame t is ``sensors.observe`` of state t plus ``action`` = the ego action applied from t to t+1
    (``ego_action`` of state t+1). Returns (state after the last step, i.e. the state of the next
    frame, so rollouts chain; frames: dict of [num_frames, ...] arrays).

    The world is stepped first and the sensors observe all recorded states at once: one wide vmapped
    pass instead of one narrow pass per scan step (the same frames; a few % faster for a `cpu` batch,
    BUILD_NOTES.md).
    """
    def body(state, _):
        next_state = world.step(state, town)
        return next_state, (state, next_state.ego_action)

    last, (states, actions) = jax.lax.scan(body, state, None, length=num_frames)
    frames = jax.vmap(lambda s: sensors.observe(s, town, image_size))(states)
    return last, {**frames, "action": actions}


def sequence(key, town, cfg: config_lib.Config):
    """One recorded sequence: dict of [T+1, ...] arrays (T = cfg.data.seq_len)."""
    state = world.reset(key, town, cfg.world)
    state = jax.lax.fori_loop(0, cfg.data.warmup_steps, lambda _, s: world.step(s, town), state)
    _, frames = rollout(state, town, cfg.data.seq_len + 1, cfg.data.image_size)
    return frames


@functools.partial(jax.jit, static_argnames="cfg")
def make_batch(key, town, cfg: config_lib.Config):
    """A batch (dict of [B, T+1, ...] arrays, see the module docstring) from ``key`` alone.

    ``cfg`` is static (hashable frozen dataclasses); the same key, town and config give a bit-identical
    batch.
    """
    keys = jax.random.split(key, cfg.data.batch_size)
    return jax.vmap(lambda k: sequence(k, town, cfg))(keys)


def batch_key(seed: int, step: int):
    """The key of training step ``step``'s batch: a resumed run sees the same data at the same step."""
    return jax.random.fold_in(jax.random.PRNGKey(seed), step)


def batch_stream(town, cfg: config_lib.Config, seed: int, start_step: int = 0):
    """Yields (step, batch) for step = start_step, start_step + 1, ... with batch_key(seed, step)."""
    step = start_step
    while True:
        yield step, make_batch(batch_key(seed, step), town, cfg)
        step += 1
