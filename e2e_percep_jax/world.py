"""Traffic and ego in pure JAX: ``reset(key, town, cfg)`` and ``step(state, town)``."""
from typing import NamedTuple

import jax

EGO = 0  # index of the ego in every per-vehicle array


class WorldState(NamedTuple):
    """One world. Field names marked (sensors) are relied on by ``sensors.py``: do not rename.

    All per-vehicle arrays have N + 1 rows, the ego at row ``EGO``.
    veh_box (sensors): float32 [N+1, 5], town-frame (x, y, yaw, length, width), metres / radians.
    veh_speed_mps (sensors): float32 [N+1].
    veh_height_m (sensors): float32 [N+1].
    veh_color (sensors): uint8 [N+1, 3].
    ego_action (sensors): float32 [2], (acceleration m/s^2, steering rad) applied in the step that
        produced this state (zeros after reset). The frame contract's action at t is the
        ``ego_action`` of state t+1.
    key: PRNG key for the world's own randomness.
    """
    veh_box: jax.Array
    veh_speed_mps: jax.Array
    veh_height_m: jax.Array
    veh_color: jax.Array
    ego_action: jax.Array
    key: jax.Array
