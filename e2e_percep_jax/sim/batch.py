"""Training batches generated on the fly, in one jit: reset B worlds, warm their traffic up, drive and observe.

A batch is :class:`e2e_percep_jax.sim.rollout.Frames` (the frame contract, field by field with units and
shapes) with leading [B, T+1] axes. Every sequence starts from a fresh ``world.reset`` with its own key
and records after ``cfg.data.warmup_steps`` steps (steady traffic), so a batch depends only on its key
and successive batches are independent. Nothing touches the disk.

Opt-in, ``--data.batches_per_drive=K`` > 1: each drive of B worlds feeds K batches, each the next T+1
frames, so the 200 warm-up steps are paid once per K batches (most of a batch's cost at the `cpu`
config). Before each segment the ego role passes to a random NPC of its world (``world.hand_over_ego``):
the traffic goes on, but every batch is seen from B fresh places, so the sequences are not continuations
of the last visit's. With ``--data.carry_state`` there is no hand-over: segment j + 1 of a drive
continues segment j frame for frame (training then carries the latent across). The stream keeps K drives
and takes its batches from them in turn (step s from drive slot s % K), so successive batches come from
independent worlds; a drive is revisited every K steps, K times, then replaced by a fresh one. Batch s is still a function of (seed, s)
alone: a stream resumed at s re-drives each slot's worlds from their reset, hand-overs included, without
observing.

Opt-in, ``--data.vanish_share`` > 0 (a memory lever): in that share of the sequences one vehicle the lidar
sees in the first frame vanishes from every sensor from a random later frame on, while the targets keep it
(:func:`vanishing`). Opt-in, ``--data.occluder_share`` > 0 (another): in that share of the sequences a
phantom wall slides in across the line of sight to one vehicle the lidar sees in the first frame, from a
random later frame on, so its beams stop short and the vehicle lies in the wall's shadow while the targets
keep it (:func:`occluding`). Both change what the sensors see, never the traffic, so the batch's worlds,
targets and commands are those of the same key without them.
"""

import functools

import jax
import jax.numpy as jnp

from e2e_percep_jax import config as config_lib
from e2e_percep_jax.sim import rollout, sensors, world

PLACE_STREAM = 2**20  # fold_in data of the place frames' key: above every segment index
VANISH_STREAM = 2**21  # fold_in data of the vanishing vehicles' key: above the place stream's
OCCLUDER_STREAM = 2**22  # fold_in data of the phantom occluders' key: above the vanishing vehicles'
OCCLUDER_SLIDE_FRAMES = 3  # frames (0.3 s) over which a phantom wall slides across a vehicle: a sliver first
OCCLUDED_MIN_DISTANCE_M = 6.0  # a vehicle occluded on purpose is at least this far in the first frame


def warm_up(key, town, cfg: config_lib.Config):
    """B worlds reset from ``key`` and driven ``warmup_steps`` steps, unobserved."""

    def one(k):
        return rollout.advance(world.reset(k, town, cfg.world), town, cfg.data.warmup_steps)

    return jax.vmap(one)(jax.random.split(key, cfg.data.batch_size))


def _seen_vehicle(state, key, share, town, cfg: config_lib.Config, min_distance_m=0.0):
    """(whether this sequence draws one, the vehicle drawn, the frame [1, T] from which it is lost): with
    probability ``share``, one vehicle in view, at least ``min_distance_m`` away, whose box a lidar beam ends
    on in ``state``'s frame, drawn uniformly among them (none if there is none)."""
    k_on, k_vehicle, k_frame = jax.random.split(key, 3)
    first = sensors.observe(state, town, cfg.data.image_size, scan=False)  # XLA keeps its lidar alone
    far = jnp.linalg.norm(first["boxes"][:, :2], axis=-1) >= min_distance_m
    seen = first["boxes_lidar_visible"] & first["boxes_valid"] & far  # [N]
    vehicle = jax.random.categorical(k_vehicle, jnp.where(seen, 0.0, -jnp.inf))
    on = (jax.random.uniform(k_on) < share) & jnp.any(seen)
    return on, vehicle, jax.random.randint(k_frame, (), 1, cfg.data.seq_len + 1)


def vanishing(states, key, town, cfg: config_lib.Config):
    """The vehicles hidden from the sensors in each frame of the B sequences from ``states``, bool
    [B, T+1, N], or None when ``data.vanish_share`` is 0: in that share of the sequences, one vehicle the
    lidar sees in the first frame (:func:`_seen_vehicle`) vanishes from every sensor from a frame drawn
    uniformly in [1, T] to the last. The targets keep it, so the sequence holds a remembered vehicle
    (``metrics.box_groups``: seen earlier, by neither sensor now)."""
    if not cfg.data.vanish_share:
        return None

    def one(state, k):
        on, vehicle, start = _seen_vehicle(state, k, cfg.data.vanish_share, town, cfg)
        gone = jnp.arange(cfg.data.seq_len + 1) >= start  # [T+1]
        return on & gone[:, None] & (jnp.arange(cfg.world.num_vehicles) == vehicle)[None]

    return jax.vmap(one)(states, jax.random.split(key, cfg.data.batch_size))


def occluding(states, key, town, cfg: config_lib.Config):
    """The phantom wall of each frame of the B sequences from ``states`` (``sensors.observe``'s
    ``occluder``: ``vehicle`` int32, ``cover`` and ``side`` float32, each [B, T+1]), or None when
    ``data.occluder_share`` is 0: in that share of the sequences, one vehicle the lidar sees in the first
    frame, at least ``OCCLUDED_MIN_DISTANCE_M`` away (:func:`_seen_vehicle`), is covered by a wall that,
    from a frame drawn uniformly in [1, T], slides across its line of sight from a random side over
    ``OCCLUDER_SLIDE_FRAMES`` frames and stays to the last, following it. The beams stop at the wall and the
    vehicle lies in its shadow, as behind a building, while the targets keep it."""
    if not cfg.data.occluder_share:
        return None
    frames = cfg.data.seq_len + 1

    def one(state, k):
        k_draw, k_side = jax.random.split(k)
        on, vehicle, start = _seen_vehicle(state, k_draw, cfg.data.occluder_share, town, cfg, OCCLUDED_MIN_DISTANCE_M)
        cover = jnp.clip((jnp.arange(frames) - start + 1) / OCCLUDER_SLIDE_FRAMES, 0.0, 1.0)
        side = jnp.where(jax.random.bernoulli(k_side), 1.0, -1.0)
        return {
            "vehicle": jnp.full(frames, vehicle, jnp.int32),
            "cover": jnp.where(on, cover, 0.0).astype(jnp.float32),
            "side": jnp.full(frames, side, jnp.float32),
        }

    return jax.vmap(one)(states, jax.random.split(key, cfg.data.batch_size))


def _drive_on(states, key, stream, town, cfg: config_lib.Config):
    """(states T+1 steps later, batch of the T+1 frames from ``states``, with the vanishing vehicles and
    phantom occluders that ``key`` draws, folded with ``stream`` + each one's stream)."""
    drive = functools.partial(rollout.drive, town=town, num_frames=cfg.data.seq_len + 1, image_size=cfg.data.image_size)
    hidden = vanishing(states, jax.random.fold_in(key, VANISH_STREAM + stream), town, cfg)
    occluder = occluding(states, jax.random.fold_in(key, OCCLUDER_STREAM + stream), town, cfg)
    return jax.vmap(lambda s, h, o: drive(s, hidden=h, occluder=o))(states, hidden, occluder)


def place_points(key, town, num: int):
    """``num`` points drawn uniformly over the town's lanes: (lane [num] int32, chosen with probability
    proportional to its length; arc [num] m, uniform along it; speed [num] m/s, uniform up to its limit)."""
    k_lane, k_arc, k_speed = jax.random.split(key, 3)
    length = town.lane_length_m
    lane = jax.random.choice(k_lane, length.shape[0], (num,), p=length / jnp.sum(length))
    return (
        lane,
        jax.random.uniform(k_arc, (num,)) * length[lane],
        jax.random.uniform(k_speed, (num,)) * town.lane_speed_limit_mps[lane],
    )


def place_frames(states, key, town, cfg: config_lib.Config) -> dict:
    """The place stream: P = ``cfg.data.place_frames`` single frames (``sensors.observe``'s dict, without the
    lidar scan as in the batch's frames, [P, ...]), each seen from a :func:`place_points` point, heading along
    its lane, in the traffic of one of the B worlds ``states`` drawn uniformly (``world.place_ego``)."""
    k_world, k_points = jax.random.split(key)
    p = cfg.data.place_frames
    lane, arc, speed = place_points(k_points, town, p)
    chosen = jax.tree.map(lambda x: x[jax.random.randint(k_world, (p,), 0, cfg.data.batch_size)], states)
    placed = jax.vmap(world.place_ego, in_axes=(0, None, 0, 0, 0))(chosen, town, lane, arc, speed)
    return jax.vmap(lambda st: sensors.observe(st, town, cfg.data.image_size, scan=False))(placed)


def _with_places(frames, states, key, town, cfg: config_lib.Config):
    """``frames``, with the place stream (``place_<field>`` [P, ...]) when the config has one."""
    if not cfg.data.place_frames:
        return frames
    return dict(frames, **{f"place_{k}": v for k, v in place_frames(states, key, town, cfg).items()})


@functools.partial(jax.jit, static_argnames="cfg")
def make_batch(key, town, cfg: config_lib.Config):
    """A batch (:class:`~e2e_percep_jax.sim.rollout.Frames` [B, T+1, ...]) from ``key`` alone; with the place
    stream, a dict of its fields and the place frames (:func:`place_frames`, from the worlds after the drive).

    ``cfg`` is static (hashable frozen dataclasses); the same key, town and config give a bit-identical
    batch.
    """
    states, frames = _drive_on(warm_up(key, town, cfg), key, 0, town, cfg)
    return _with_places(frames, states, jax.random.fold_in(key, PLACE_STREAM), town, cfg)


def _hand_over(states, drive_key, segment, town, cfg: config_lib.Config):
    """Each of the B worlds hands its ego role to a random NPC, keyed by (drive, segment); with
    ``data.carry_state`` the egos keep driving (a drive's segments are then one continuous sequence)."""
    if cfg.data.carry_state:
        return states
    keys = jax.random.split(jax.random.fold_in(drive_key, segment), cfg.data.batch_size)
    vehicles = jax.vmap(lambda k: jax.random.randint(k, (), 1, cfg.world.num_vehicles + 1))(keys)
    return jax.vmap(world.hand_over_ego, in_axes=(0, 0, None))(states, vehicles, town)


@functools.partial(jax.jit, static_argnames="cfg")
def start_drive(drive_key, town, cfg: config_lib.Config, segments):
    """A drive's B worlds ready for segment ``segments``: warmed up, then ``segments`` segments driven
    unobserved, each after its hand-over (``segments`` traced: one compilation for every resume)."""

    def segment(j, states):
        states = _hand_over(states, drive_key, j, town, cfg)
        return jax.vmap(lambda s: rollout.advance(s, town, cfg.data.seq_len + 1))(states)

    return jax.lax.fori_loop(0, segments, segment, warm_up(drive_key, town, cfg))


@functools.partial(jax.jit, static_argnames="cfg")
def drive_segment(states, drive_key, segment, town, cfg: config_lib.Config):
    """(states after, batch): segment ``segment`` of a drive, seen by the egos its hand-over picks (with the
    place stream, its place frames from the worlds after the segment)."""
    states = _hand_over(states, drive_key, segment, town, cfg)
    states, frames = _drive_on(states, drive_key, segment, town, cfg)
    return states, _with_places(frames, states, jax.random.fold_in(drive_key, PLACE_STREAM + segment), town, cfg)


def batch_key(seed: int, step: int):
    """The key of training step ``step``'s batch: a resumed run sees the same data at the same step.
    With ``batches_per_drive`` K > 1 it keys drive ``drive_slot(step, K)[0]`` instead."""
    return jax.random.fold_in(jax.random.PRNGKey(seed), step)


def drive_slot(step: int, per_drive: int):
    """(drive index, segment): step ``step``'s batch is segment ``segment`` (frames [segment (T+1),
    (segment + 1)(T+1)) after the warm-up) of drive ``drive index``. Slot ``step % K`` serves steps
    s, s + K, s + 2K, ...; each of its drives lasts K of them, so drive g serves the steps
    (g // K) K^2 + g % K + j K, j < K. K = 1: drive s, segment 0."""
    slot, visit = step % per_drive, step // per_drive
    generation, segment = divmod(visit, per_drive)
    return generation * per_drive + slot, segment


def batch_stream(town, cfg: config_lib.Config, seed: int, start_step: int = 0):
    """Yields (step, batch) for step = start_step, start_step + 1, ...

    With ``cfg.data.batches_per_drive`` K = 1 (default) the batch of step s is
    ``make_batch(batch_key(seed, s))``. With K > 1 it is segment ``j`` of the drives keyed
    ``batch_key(seed, g)``, ``(g, j) = drive_slot(s, K)``.
    """
    per_drive, step = cfg.data.batches_per_drive, start_step
    if per_drive == 1:
        while True:
            yield step, make_batch(batch_key(seed, step), town, cfg)
            step += 1
    slots = [None] * per_drive  # per slot: the B world states its drive has reached
    while True:
        drive, segment = drive_slot(step, per_drive)
        slot, drive_key = step % per_drive, batch_key(seed, drive)
        if slots[slot] is None or segment == 0:
            slots[slot] = start_drive(drive_key, town, cfg, segment)
        slots[slot], frames = drive_segment(slots[slot], drive_key, segment, town, cfg)
        yield step, frames
        step += 1
