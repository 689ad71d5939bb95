"""Driving the world: the one loop over ``world.step`` and ``sensors.observe``.

Everything that drives a world goes through here:

- :func:`advance`: steps without observing (the traffic's warm-up; re-driving a drive to where a
  resumed run stopped);
- :func:`drive`: steps ``num_frames`` times, observing every state before its step, and returns the
  drive as :class:`Frames` (training batches, pictures of the world);
- :func:`drive_perceiving`: the same loop with a perceiver inside it, frame by frame, so that frame t is
  perceived before the world moves on (the online evaluation).

All three work on one world; ``jax.vmap`` them over worlds.
"""

from collections.abc import Callable, Mapping

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax.sim import sensors, world

NEVER_SEEN = np.iinfo(np.int32).max  # boxes_frames_since_seen of a vehicle not seen since the drive began


@flax.struct.dataclass
class Frames(Mapping):
    """The frame contract over a drive: every field has leading axes ``[..., T]`` (a batch's are
    ``[B, T+1]``). Also a read-only mapping by field name (``frames["camera"]``), as the loss reads it.

    camera, lidar, roadmap: uint8 [..., R, R, 3], the ego's views (R = ``data.image_size`` pixels a side);
    lidar_scan: float32 [..., 360], the lidar's own ranges (m) per degree of azimuth, anticlockwise from
    ahead: its nearest return above the ground band, 0 where none within its 50 m (``sensors.render_scan``;
    the lidar odometry's, which the model never reads; None in drives that skip it, as training batches do);
    det_cls: float32 [..., R, R, 1], 1 on pixels inside a vehicle's box; det_reg: float32 [..., R, R, 6],
    PIXOR regression targets (units in :mod:`e2e_percep_jax.sim.pixor`); pose: float32 [..., 5], the ego's
    (x m, y m, cos yaw, sin yaw, speed m/s) in the town frame; action: float32 [..., 2], the ego's commands
    from this frame to the next, as a car logs them: (pedal in [-1, 1], steering command rad); the plant
    that turns them into motion (``world.EgoPlant``) is not part of the contract; boxes: float32 [..., N, 5],
    the N other vehicles in the ego frame (x m, y m, yaw rad, length m, width m), in the world's vehicle
    order; boxes_valid: bool [..., N], inside the bird-eye view. Who saw each vehicle, for the evaluation
    (the model never reads them): boxes_lidar_visible: bool [..., N], some lidar beam ends on it;
    boxes_camera_visible: bool [..., N], the camera image shows some of it (after the depth test, at R
    pixels); boxes_frames_since_seen: int32 [..., N], frames (0.1 s each) since either sensor last saw
    it: 0 when one sees it now, ``NEVER_SEEN`` when none has since the drive's first frame.
    """

    camera: jax.Array
    lidar: jax.Array
    lidar_scan: jax.Array
    roadmap: jax.Array
    det_cls: jax.Array
    det_reg: jax.Array
    pose: jax.Array
    action: jax.Array
    boxes: jax.Array
    boxes_valid: jax.Array
    boxes_lidar_visible: jax.Array
    boxes_camera_visible: jax.Array
    boxes_frames_since_seen: jax.Array

    def __getitem__(self, name):
        if name not in self.__dataclass_fields__:
            raise KeyError(name)
        return getattr(self, name)

    def __iter__(self):
        return iter(self.__dataclass_fields__)

    def __len__(self):
        return len(self.__dataclass_fields__)


def since_seen_step(frames_since_seen, frame):
    """Frames since each vehicle was last seen, int32 [..., N], after ``frame`` (``sensors.observe``'s
    dict): 0 where a sensor sees it now, else one more than before (``NEVER_SEEN`` stays)."""
    seen = frame["boxes_lidar_visible"] | frame["boxes_camera_visible"]
    return jnp.where(seen, 0, jnp.where(frames_since_seen == NEVER_SEEN, NEVER_SEEN, frames_since_seen + 1))


def frames_since_seen(frames: dict) -> jax.Array:
    """``boxes_frames_since_seen`` [T, N] of a drive's observed frames ([T, ...]), counted from frame 0."""
    never = jnp.full(frames["boxes_lidar_visible"].shape[1:], NEVER_SEEN, jnp.int32)
    step = lambda since, frame: (since_seen_step(since, frame),) * 2
    seen = {k: frames[k] for k in ("boxes_lidar_visible", "boxes_camera_visible")}
    return jax.lax.scan(step, never, seen)[1]


def advance(state: world.WorldState, town, num_steps) -> world.WorldState:
    """``state`` after ``num_steps`` world steps (an int, or traced), unobserved."""
    return jax.lax.fori_loop(0, num_steps, lambda _, s: world.step(s, town), state)


def drive(
    state: world.WorldState,
    town,
    num_frames: int,
    image_size: int,
    with_states: bool = False,
    scans: bool = False,
    hidden=None,
    occluder=None,
):
    """Drives ``num_frames`` world steps from ``state``, observing before each step.

    Frame t is ``sensors.observe`` of state t plus ``action`` = the ego action applied from t to t+1
    (``ego_action`` of state t+1). Returns (the state after the last step, i.e. the state of the next
    frame, so drives chain; :class:`Frames` [num_frames, ...], its ``lidar_scan`` cast only with ``scans``:
    the lidar odometry's, which no model reads, at a quarter of a frame's cost; else None),
    and with ``with_states`` the world states the frames saw ([num_frames, ...]) as a third element.
    ``hidden``, bool [num_frames, N] or None: the vehicles no sensor sees in each frame; ``occluder``, a dict
    of arrays [num_frames] or None: a phantom wall in each frame (both ``sensors.observe``'s).

    The world is stepped first and the sensors observe all recorded states at once: one wide vmapped
    pass instead of one narrow pass per scan step (the same frames, and a few % faster).
    """

    def body(state, _):
        next_state = world.step(state, town)
        return next_state, (state, next_state.ego_action)

    last, (states, actions) = jax.lax.scan(body, state, None, length=num_frames)
    # None is an empty pytree: vmap passes it through as None
    frames = jax.vmap(lambda s, h, o: sensors.observe(s, town, image_size, scans, h, o))(states, hidden, occluder)
    frames.setdefault("lidar_scan", None)
    frames = Frames(**frames, action=actions, boxes_frames_since_seen=frames_since_seen(frames))
    return (last, frames, states) if with_states else (last, frames)


def drive_perceiving(world_state, perceiver_state, since, town, image_size: int, keys, warming, perceive: Callable):
    """``len(keys)`` frames of W worlds (``world_state`` batched over W), each observed and perceived before
    the worlds step: a ``lax.scan`` whose carry is (world state, perceiver state), so memory does not grow
    with the drive.

    ``perceive(perceiver_state, frame, prev_action, key) -> (perceiver_state, out)`` sees frame t of the W
    worlds (``sensors.observe``'s dict with ``boxes_frames_since_seen``, [W, ...]) and ``prev_action``
    [W, 2], the ego action applied from t-1 to t (meaningless on a drive's first frame). ``warming`` bool
    [C]: frames that only step the worlds (traffic warm-up: nothing observed or perceived; their ``out`` is
    zeros), decided at run time, so one compiled program serves warm-up and driven frames; the drive, and
    its count of frames since each vehicle was seen, starts at the first frame that is not warming.
    ``since`` int32 [W, N]: that count before the chunk (``NEVER_SEEN`` to start a drive). Returns (world
    state, perceiver state, ``since`` after the chunk, ``out`` stacked [C, ...]).
    """
    observe = jax.vmap(lambda s: sensors.observe(s, town, image_size))
    step = jax.vmap(lambda s: world.step(s, town))

    # (jitted so that the shape query below and the scan's branch share one trace: the sensors and the
    # perceiver are traced once, not twice)
    @jax.jit
    def seen(wstate, pstate, since, key):
        frame = observe(wstate)
        frame["boxes_frames_since_seen"] = since = since_seen_step(since, frame)
        # state t's ego_action is the action applied from t-1 to t
        return perceive(pstate, frame, wstate.ego_action, key) + (since,)

    shapes = jax.eval_shape(lambda: seen(world_state, perceiver_state, since, keys[0])[1])
    zeros = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)

    def body(carry, xs):
        wstate, pstate, since = carry
        key, warm = xs
        never = jnp.full_like(since, NEVER_SEEN)
        pstate, out, since = jax.lax.cond(
            warm, lambda: (pstate, zeros, never), lambda: seen(wstate, pstate, since, key)
        )
        return (step(wstate), pstate, since), out

    carry = (world_state, perceiver_state, since)
    (world_state, perceiver_state, since), out = jax.lax.scan(body, carry, (keys, warming))
    return world_state, perceiver_state, since, out
