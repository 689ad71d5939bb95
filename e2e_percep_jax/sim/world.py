"""Traffic and ego in pure JAX: ``reset(key, town, cfg)`` and ``step(state, town)``.

Every vehicle lives on a lane at an arc position (its centre) and carries a planned route: the next
ROUTE_LEN lanes, each picked at random among its predecessor's successors (so vehicles take random exits).
Longitudinal control is IDM against the nearest of:

- the leader: the first vehicle body ahead along the route (same lane, or the lanes after it, including a
  body whose rear still hangs back onto a lane the follower is on);
- a stop line whose light is red (or yellow, when the vehicle can stop comfortably);
- the mouth of a junction whose exit is queued ("don't block the junction"): a vehicle that has stood at such a
  mouth for REROUTE_AFTER_S takes another exit with room, if there is one (see ``_reroute``), so a ring of
  queues, each waiting for room on the next, does not stand still for good;
- a conflict zone it must yield at (see ``Town.conf_*``): a vehicle may not enter its lane's zone of a
  conflict while a vehicle body lies in the other lane's zone, nor while a vehicle of higher priority is
  approaching that zone. Priority is, in order: cannot stop before the zone any more; the lane's right of
  way (the ring over its entries); the lower vehicle index. A total order cannot wait on itself in a
  circle; vehicles that diverge from the same lane skip the priority rule (the one ahead goes first).

An NPC never moves into its leader's rear, across a red stop line or into a zone it yields at (its step is
clamped), and sits on its lane's centre line. The ego runs the same autopilot, but what it decides are
commands, clipped to their limits: a pedal in [-1, 1] (times EGO_ACCEL_LIMIT_MPS2, the acceleration asked
for) and a steering command (a road-wheel angle in radians; curvature feed-forward plus feedback on the
rear axle's lateral and heading error). A plant with hidden per-drive parameters (:class:`EgoPlant`) turns
the commands into motion: first-order actuator lag, a steering offset and gain, a distance scale (the
wheels' true radius against the nominal), understeer (tyre slip growing with lateral acceleration), and
per-step noise on acceleration and curvature, through a kinematic bicycle model. The commands are what a
perceiver is given (the frame contract's ``action``); the plant's parameters never are.

Shapes: N + 1 vehicles (the ego is row EGO), L = ROUTE_LEN + 1 lanes on the known path (the current
one first), MC conflicts per lane, NL lanes.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax.config import WorldConfig
from e2e_percep_jax.sim import motion
from e2e_percep_jax.sim import town as town_lib
from e2e_percep_jax.sim.geometry import wrap_angle
from e2e_percep_jax.sim.motion import DT_S, EGO_ACCEL_LIMIT_MPS2, WHEELBASE_M, centre_after

EGO = 0  # index of the ego in every per-vehicle array

ROUTE_LEN = 3
# Conflict zones are checked on the current lane and the next two: a zone on the lane after those is at least
# the two lanes' length (> 20 m, tested) away, and it is checked once it becomes the third.
CONFLICT_LANES = 3
EGO_STEER_LIMIT_RAD = 0.3
EGO_SIZE_M = (4.6, 1.9, 1.5)  # length, width, height
EGO_COLOR = (200, 30, 40)
STEER_GAIN_LATERAL = 0.1  # 1/m^2: curvature command per metre of lateral error
STEER_GAIN_HEADING = 0.6  # 1/m: per unit sin(heading error); critically damped with the lateral gain
IDM_HEADWAY_S = 1.0
IDM_MIN_GAP_M = 2.0
COMFORT_DECEL_MPS2 = 2.5
NPC_MAX_DECEL_MPS2 = 6.0
STOP_SHORT_M = town_lib.STOP_BAR_M  # vehicles rest this far before a stop line (at its painted bar) or a zone
LEADER_CLEARANCE_M = 0.5  # an NPC never steps closer than this to its leader's rear (curves need > 0.4)
BODY_MARGIN_M = 0.3  # added to both ends of a body against conflict zones: box corners on curves reach further
START_TIME_RANGE_S = 3600.0  # reset draws the clock uniformly from [0, this): lights start in any phase
STANDING_MPS = 0.1  # slower than this counts as standing
# Two full light cycles (<= 56 s each) of standing at a queued mouth: traffic that is only slow discharges its
# exit within that time; a ring of full roads never does. No drive shorter than this can re-route.
REROUTE_AFTER_S = 120.0

_CAR_PAINTS = np.array(
    [
        [235, 235, 235],
        [25, 25, 28],
        [170, 172, 178],
        [95, 98, 105],
        [30, 45, 110],
        [180, 25, 30],
        [40, 90, 190],
        [30, 100, 60],
        [230, 200, 40],
        [220, 110, 30],
        [110, 70, 45],
        [200, 185, 150],
    ],
    np.int32,
)


class WorldState(NamedTuple):
    """One world. Field names marked (sensors) are relied on by ``sensors.py``: do not rename.

    All per-vehicle arrays have N + 1 rows, the ego at row ``EGO``.
    veh_box (sensors): float32 [N+1, 5], town-frame (x, y, yaw, length, width), metres / radians.
    veh_speed_mps (sensors): float32 [N+1].
    veh_height_m (sensors): float32 [N+1].
    veh_color (sensors): uint8 [N+1, 3].
    ego_action (sensors): float32 [2], the ego's commands (pedal in [-1, 1], steering command rad) in the
        step that produced this state (zeros after reset). The frame contract's action at t is the
        ``ego_action`` of state t+1.
    ego_actuator: float32 [2], the actuators' state after that step: (acceleration the pedal has reached
        m/s^2, road-wheel angle the steering has reached rad), before the plant's gain and offset.
    ego_plant: :class:`EgoPlant`, the ego's hidden parameters, drawn at reset.
    key: PRNG key for the world's own randomness.
    veh_lane: int32 [N+1], the lane the vehicle's centre is on.
    veh_s_m: float32 [N+1], arc position of the centre along that lane (the ego's: its projection).
    veh_prev_lane: int32 [N+1], the lane before (where a body's rear may still be), -1 after reset.
    veh_route: int32 [N+1, ROUTE_LEN], the next lanes the vehicle will take, in order.
    veh_max_accel_mps2: float32 [N+1], IDM's maximum acceleration (a driver trait).
    veh_speed_frac: float32 [N+1], desired speed as a fraction of the speed limit (a driver trait).
    veh_standing_steps: int32 [N+1], steps since the vehicle last moved (or last re-routed).
    step: int32 [], time index; the clock (lights) reads ``step * DT_S`` seconds.
    """

    veh_box: jax.Array
    veh_speed_mps: jax.Array
    veh_height_m: jax.Array
    veh_color: jax.Array
    ego_action: jax.Array
    ego_actuator: jax.Array
    ego_plant: "EgoPlant"
    key: jax.Array
    veh_lane: jax.Array
    veh_s_m: jax.Array
    veh_prev_lane: jax.Array
    veh_route: jax.Array
    veh_max_accel_mps2: jax.Array
    veh_speed_frac: jax.Array
    veh_standing_steps: jax.Array
    step: jax.Array


class EgoPlant(NamedTuple):
    """What turns the ego's commands into motion, per drive (float32 [] each); never shown to a perceiver.

    The road-wheel angle is ``steer_gain * actuator + steer_offset_rad``; the bicycle's curvature is
    ``tan(angle) / (WHEELBASE_M + understeer_rad_s2pm * v^2)`` (the understeer gradient: slip grows with
    lateral acceleration v^2 kappa); the acceleration the pedal's actuator reaches moves the car
    ``distance_scale`` times as far as the nominal wheel radius says.
    """

    steer_offset_rad: jax.Array
    steer_gain: jax.Array
    distance_scale: jax.Array
    understeer_rad_s2pm: jax.Array  # road-wheel angle per m/s^2 of lateral acceleration
    lag_share: jax.Array  # share of the gap to the command the actuators close in a step (1: no lag)
    accel_noise_mps2: jax.Array  # per-step std
    curvature_noise_1pm: jax.Array  # per-step std (a standing car does not turn)


PLANT_TRUNCATION = 2.5  # the per-drive draws are normal, truncated at this many stds
G_MPS2 = 9.81


def draw_plant(key, cfg: WorldConfig) -> EgoPlant:
    """One drive's :class:`EgoPlant`: offset, gain and distance scale drawn around (0, 1, 1) with the
    config's stds; lag, understeer and noise as configured. All-zero fields give the exact plant."""
    offset, gain, scale = jax.random.truncated_normal(key, -PLANT_TRUNCATION, PLANT_TRUNCATION, (3,))
    f32 = lambda x: jnp.float32(x)
    return EgoPlant(
        steer_offset_rad=offset * f32(np.deg2rad(cfg.ego_steer_offset_deg)),
        steer_gain=1.0 + gain * f32(cfg.ego_steer_gain_std),
        distance_scale=1.0 + scale * f32(cfg.ego_distance_scale_std),
        understeer_rad_s2pm=f32(np.deg2rad(cfg.ego_understeer_deg_per_g) / G_MPS2),
        lag_share=f32(motion.lag_share(cfg.ego_lag_s)),
        accel_noise_mps2=f32(cfg.ego_accel_noise_mps2),
        curvature_noise_1pm=f32(cfg.ego_curvature_noise_1pm),
    )


def lane_point(town, lane, s_m):
    """Point on lanes ``lane`` [...] at arcs ``s_m`` [...]: (xy [..., 2], yaw [...], curvature [...]).

    Linear between the stored samples; before the start it extrapolates along the first sample's heading,
    past the end it continues straight (the stored samples do).
    """
    num_samples = town.lane_xy_m.shape[1]
    pos = s_m / town_lib.LANE_DS_M
    i0 = jnp.clip(jnp.floor(pos).astype(jnp.int32), 0, num_samples - 2)
    frac = pos - i0
    xy0, xy1 = town.lane_xy_m[lane, i0], town.lane_xy_m[lane, i0 + 1]
    yaw0, yaw1 = town.lane_yaw_rad[lane, i0], town.lane_yaw_rad[lane, i0 + 1]
    inside = jnp.clip(frac, 0.0, 1.0)
    yaw = yaw0 + inside * wrap_angle(yaw1 - yaw0)
    curv = town.lane_curv_1pm[lane, i0] * (1 - inside) + town.lane_curv_1pm[lane, i0 + 1] * inside
    return xy0 + frac[..., None] * (xy1 - xy0), yaw, curv


def _pick_successor(town, lane, key):
    """A random successor of each lane [M] (uniform up to 2^-32).

    One random word from ``key``, spread over the M vehicles by an integer hash (the murmur3 finaliser of
    word + row): far cheaper than M threefry draws, and as random for choosing among <= 3 exits.
    """
    h = _row_hash(key, lane.shape[0])
    return town.lane_succ[lane, (h % town.lane_num_succ[lane].astype(jnp.uint32)).astype(jnp.int32)]


def _row_hash(key, num_rows: int):
    """uint32 [num_rows]: one random word from ``key``, spread over the rows by the murmur3 finaliser."""
    h = jax.random.bits(key, (), jnp.uint32) + jnp.arange(num_rows, dtype=jnp.uint32) * jnp.uint32(0x9E3779B9)
    for shift, mult in ((16, 0x85EBCA6B), (13, 0xC2B2AE35)):
        h = (h ^ (h >> shift)) * jnp.uint32(mult)
    return h ^ (h >> 16)


def _check_fits(num_vehicles: int, num_slots: int) -> None:
    if num_vehicles + 1 > min(num_slots, MAX_VEHICLES):
        raise ValueError(
            f"--world.num_vehicles={num_vehicles}: at most {min(num_slots, MAX_VEHICLES) - 1} "
            "fit (spawn slots of this town, and the world's vehicle limit)"
        )


def check_vehicle_count(cfg: WorldConfig, town_seed: int) -> None:
    """:func:`reset`'s check, before anything is compiled or written: raises ValueError naming
    ``--world.num_vehicles`` unless that many NPCs and the ego fit the town of ``town_seed``."""
    _check_fits(cfg.num_vehicles, town_lib.spawn_slots(town_seed))


def reset(key, town, cfg: WorldConfig) -> WorldState:
    """A world with cfg.num_vehicles NPCs and the ego on distinct random spawn slots, at random safe speeds."""
    n = cfg.num_vehicles + 1
    num_slots = town.spawn_lane.shape[0]
    _check_fits(cfg.num_vehicles, num_slots)
    keys = jax.random.split(key, 12)
    slot = jax.random.permutation(keys[0], num_slots)[:n]
    lane, s = town.spawn_lane[slot], town.spawn_s_m[slot]
    # Small cars to vans: width and height grow with length.
    size = jax.random.uniform(keys[1], (n,))
    length = 3.7 + 1.8 * size
    width = jnp.clip(1.6 + 0.5 * size + jax.random.uniform(keys[2], (n,), minval=-0.06, maxval=0.06), 1.6, 2.1)
    height = jnp.clip(1.4 + 0.9 * size**2 + jax.random.uniform(keys[3], (n,), minval=-0.1, maxval=0.3), 1.4, 2.6)
    length, width, height = (a.at[EGO].set(v) for a, v in zip((length, width, height), EGO_SIZE_M))
    paint = jnp.asarray(_CAR_PAINTS)[jax.random.randint(keys[4], (n,), 0, _CAR_PAINTS.shape[0])]
    color = jnp.clip(paint + jax.random.randint(keys[5], (n, 3), -12, 13), 0, 255)
    color = color.at[EGO].set(jnp.array(EGO_COLOR)).astype(jnp.uint8)
    route_keys = jax.random.split(keys[6], ROUTE_LEN)
    route = [lane]
    for k in range(ROUTE_LEN):
        route.append(_pick_successor(town, route[-1], route_keys[k]))
    speed_frac = jax.random.uniform(keys[7], (n,), minval=0.85, maxval=1.0)
    # A safe start: able to stop comfortably within the free space a slot guarantees (or before the lane end).
    free_m = jnp.minimum(town_lib.SPAWN_SPACING_M - 5.5, town.lane_length_m[lane] - s - 0.5 * length) - IDM_MIN_GAP_M
    safe_mps = jnp.sqrt(2 * COMFORT_DECEL_MPS2 * jnp.maximum(free_m, 0.0))
    speed = jax.random.uniform(keys[8], (n,)) * jnp.minimum(town.lane_speed_limit_mps[lane] * speed_frac, safe_mps)
    xy, yaw, _ = lane_point(town, lane, s)
    return WorldState(
        veh_box=jnp.concatenate([xy, yaw[:, None], length[:, None], width[:, None]], 1),
        veh_speed_mps=speed,
        veh_height_m=height,
        veh_color=color,
        ego_action=jnp.zeros(2, jnp.float32),
        ego_actuator=jnp.stack([0.0, _lane_steer(town, lane[EGO], s[EGO])]),
        # (folded, not split: the world's other draws stay what they were before the plant existed)
        ego_plant=draw_plant(jax.random.fold_in(key, len(keys)), cfg),
        key=keys[9],
        veh_lane=lane,
        veh_s_m=s,
        veh_prev_lane=jnp.full(n, -1, jnp.int32),
        veh_route=jnp.stack(route[1:], 1),
        veh_max_accel_mps2=jax.random.uniform(keys[10], (n,), minval=1.5, maxval=2.5),
        veh_speed_frac=speed_frac,
        veh_standing_steps=jnp.zeros(n, jnp.int32),
        step=jax.random.randint(keys[11], (), 0, int(START_TIME_RANGE_S / DT_S)),
    )


# Body positions packed with their vehicle into one int32 key: (position + _PACK_OFFSET_M) in 1/1024 m above
# _PACK_INDEX_BITS of vehicle index, so a min over keys is the rearmost body and whose it is. Positions on a
# lane lie within [-_PACK_OFFSET_M, _PACK_OFFSET_M) (town.MAX_LANE_LENGTH_M is shorter); MAX_VEHICLES rows.
_PACK_OFFSET_M, _PACK_STEPS_PER_M, _PACK_INDEX_BITS = 64.0, 1024, 9
MAX_VEHICLES = 2**_PACK_INDEX_BITS - 1
_NOBODY = np.int32(2**31 - 1)


def _pack(position_m, index):
    q = jnp.clip(jnp.round((position_m + _PACK_OFFSET_M) * _PACK_STEPS_PER_M), 0, 2**17 - 1).astype(jnp.int32)
    return (q << _PACK_INDEX_BITS) | index


def _unpack(key):
    """(position m, +inf for nobody; vehicle index, -1 for nobody, which picks a caller's trailing pad row)."""
    nobody = key == _NOBODY
    position = (key >> _PACK_INDEX_BITS).astype(jnp.float32) / _PACK_STEPS_PER_M - _PACK_OFFSET_M
    index = key & (2**_PACK_INDEX_BITS - 1)
    return jnp.where(nobody, jnp.inf, position), jnp.where(nobody, -1, index)


def _idm_braking(v, a_max, gap_m, closing_mps):
    """IDM's interaction term (s* / s)^2 for a gap [m] to an obstacle approached at ``closing_mps``."""
    desired_gap = IDM_MIN_GAP_M + jnp.maximum(
        0.0, v * IDM_HEADWAY_S + v * closing_mps / (2 * jnp.sqrt(a_max * COMFORT_DECEL_MPS2))
    )
    return (desired_gap / jnp.maximum(gap_m, 0.1)) ** 2


class _Plan(NamedTuple):
    """What the autopilot decided for every vehicle [N+1] this step (distances from its front)."""

    accel_mps2: jax.Array  # IDM's acceleration, before the ego's action limits
    gap_lead_m: jax.Array  # to the leader's rear (inf: none on the known path)
    d_stop_m: jax.Array  # to the stop line it stops at (red light or queued junction exit), inf if none
    d_yield_m: jax.Array  # to the nearest conflict zone it yields at, inf if none
    path: jax.Array  # int32 [N+1, L], current lane then route
    limit_mps: jax.Array  # [N+1, L], speed limits along the path
    exit_queued: jax.Array  # bool [N+1]: first on its lane, at a junction mouth whose exit is queued
    lane_rear_m: jax.Array  # [NL], arc position of the rearmost body point on each lane (inf: empty)


def _plan(state: WorldState, town) -> _Plan:
    """The autopilot of every vehicle: leader, stop lines, conflict zones, then IDM."""
    n = state.veh_s_m.shape[0]
    nl, mc = town.conf_lane.shape
    idx = jnp.arange(n, dtype=jnp.int32)
    v, s, lane, prev = state.veh_speed_mps, state.veh_s_m, state.veh_lane, state.veh_prev_lane
    half = 0.5 * state.veh_box[:, 3]
    rear, front = s - half, s + half
    a_max = state.veh_max_accel_mps2
    max_decel = jnp.full(n, NPC_MAX_DECEL_MPS2).at[EGO].set(EGO_ACCEL_LIMIT_MPS2)
    brake_m = v**2 / (2 * COMFORT_DECEL_MPS2) + v * DT_S  # room to stop without hard braking

    # The known path: the current lane, then the route. Distances from the centre to each lane's ends [N+1, L].
    path = jnp.concatenate([lane[:, None], state.veh_route], 1)
    length = town.lane_length_m[path]
    to_start = [-s]
    for k in range(ROUTE_LEN):  # unrolled: a cumsum over 4 columns is a slow reduce-window on CPU
        to_start.append(to_start[-1] + length[:, k])
    to_start = jnp.stack(to_start, 1)
    to_end = to_start + length
    front_to_end = to_end - half[:, None]

    # Leader: the first body ahead along the path. Body points are packed with their vehicle into int32 keys
    # (see _pack), so one min finds both how far and whose. On the own lane: the nearest rear ahead (a masked
    # [N+1, N+1] min: cheaper than a sort at this size). Per lane: the rearmost body point of the vehicles
    # whose centre is on it (tail), and of bodies that left it but still hang back onto it (spill).
    prev_length = town.lane_length_m[jnp.maximum(prev, 0)]
    ahead = jnp.min(
        jnp.where((lane[None, :] == lane[:, None]) & (s[None, :] > s[:, None]), _pack(rear, idx)[None, :], _NOBODY), 1
    )
    tail = jnp.full(nl, _NOBODY).at[lane].min(_pack(rear, idx))
    spill = (
        jnp.full(nl, _NOBODY)
        .at[jnp.where((rear < 0) & (prev >= 0), prev, nl)]
        .min(_pack(prev_length + rear, idx), mode="drop")
    )
    later = path[:, 1:]
    keys = jnp.concatenate([ahead[:, None], spill[lane][:, None], jnp.minimum(tail[later], spill[later])], 1)
    rear_m, owner = _unpack(keys)
    front_offset = jnp.concatenate([jnp.stack([-front, -front], 1), to_start[:, 1:] - half[:, None]], 1)
    gaps = rear_m + front_offset  # from the front, along the path
    nearest = jnp.argmin(gaps, 1)  # over 5 candidates only
    gap_lead = jnp.take_along_axis(gaps, nearest[:, None], 1)[:, 0]
    v_lead = jnp.concatenate([v, jnp.zeros(1)])[jnp.take_along_axis(owner, nearest[:, None], 1)[:, 0]]

    # Stop lines: red, or yellow when there is room to stop; and junction mouths whose exit is queued.
    lights = town_lib.light_states(town, state.step * DT_S)
    lane_light = town.lane_light[path]
    signal = jnp.where(lane_light >= 0, lights[jnp.maximum(lane_light, 0)], town_lib.LIGHT_GREEN)
    can_stop = front_to_end >= brake_m[:, None]
    red = (signal == town_lib.LIGHT_RED) | ((signal == town_lib.LIGHT_YELLOW) & can_stop)
    # Do not enter a junction unless there is room behind where the leader will come to rest.
    exit_needs_m = to_end[:, 1:-1] + half[:, None] + IDM_MIN_GAP_M  # leader's rear beyond the junction lane
    queued = (gap_lead + v_lead**2 / (2 * COMFORT_DECEL_MPS2))[:, None] < exit_needs_m
    blocked = town.lane_at_mouth[path[:, :-2]] & queued & can_stop[:, :-2]
    exit_queued = blocked[:, 0] & (gap_lead > front_to_end[:, 0])
    blocked = jnp.pad(blocked, ((0, 0), (0, 2)))
    stop_at_end = (front_to_end >= 0) & (red | blocked)
    d_stop = jnp.min(jnp.where(stop_at_end, front_to_end, jnp.inf), 1)
    first_stop = jnp.where(stop_at_end.any(1), jnp.argmax(stop_at_end, 1), path.shape[1])
    beyond_stop = jnp.arange(path.shape[1])[None] > first_stop[:, None]  # [N+1, L]

    # Conflict zones on the previous lane and the first CONFLICT_LANES of the path: rows [N+1, 1 + CONFLICT_LANES,
    # MC] (row 1 is the current lane).
    rows = jnp.concatenate([jnp.maximum(prev, 0)[:, None], path[:, :CONFLICT_LANES]], 1)
    # (The barrier makes XLA gather each table row once, instead of once per element of every fused consumer.)
    foe, mirror, by_priority, zone_in, zone_out = jax.lax.optimization_barrier(
        (
            town.conf_lane[rows],
            town.conf_mirror[rows],
            town.conf_by_priority[rows],
            town.conf_in_m[rows],
            town.conf_out_m[rows],
        )
    )
    row_start = jnp.concatenate([(-s - prev_length)[:, None], to_start[:, :CONFLICT_LANES]], 1)  # to lane starts
    d_in = row_start[:, :, None] + zone_in - (half + BODY_MARGIN_M)[:, None, None]  # front to the zone
    d_out = row_start[:, :, None] + zone_out + (half + BODY_MARGIN_M)[:, None, None]  # rear past it
    has_row = (jnp.arange(rows.shape[1]) > 0)[None, :] | (prev >= 0)[:, None]  # row 0 only if there was a prev
    valid = (foe >= 0) & has_row[:, :, None]
    occupies = valid & (d_in < 0) & (d_out > 0)
    pending = valid & (d_in >= 0)
    # Entering a junction from a road is atomic: a vehicle waits at the mouth until nothing on its junction
    # lane must be yielded, so it never stops half-way between two zones.
    mouth_m = row_start - half[:, None]
    at_mouth = jnp.concatenate([jnp.zeros((n, 2), bool), town.lane_at_mouth[path[:, : CONFLICT_LANES - 1]]], 1)
    stop_m = jnp.where((at_mouth & (mouth_m >= 0))[:, :, None], mouth_m[:, :, None], d_in)
    # Priority, highest first: cannot stop before the zone any more; inside the junction lane already; the
    # lane's right of way; the lower vehicle index. A vehicle claims the zones it occupies above all, every
    # pending zone of its current lane, and those of a later lane once that lane is within its horizon (unless
    # its leader will come to rest before that lane: then the leader's claim is the one that matters).
    committed = stop_m < (v**2 / (2 * max_decel) + v * DT_S)[:, None, None]
    inside = (jnp.arange(rows.shape[1]) == 1)[None, :, None]
    priority = (committed * 8 + inside * 4 + town.lane_priority[rows][:, :, None]) * n + (n - 1 - idx)[:, None, None]
    occupied_claim = 16 * n  # above every priority
    horizon_m = brake_m + v * 1.0 + 10.0
    leader_rest_m = gap_lead + v_lead**2 / (2 * COMFORT_DECEL_MPS2)
    near = inside | ((mouth_m <= horizon_m[:, None]) & (mouth_m <= leader_rest_m[:, None]))[:, :, None]
    not_held = jnp.concatenate([jnp.zeros((n, 1), bool), ~beyond_stop[:, :CONFLICT_LANES]], 1)[:, :, None]
    approaching = pending & by_priority & near & not_held
    claim = jnp.where(occupies, occupied_claim, jnp.where(approaching, priority, -1))
    claims = jnp.full((nl, mc), -1, jnp.int32).at[rows].max(claim).reshape(-1)
    foe_claim = claims[jnp.maximum(foe, 0) * mc + mirror]
    # Yield to a body in the foe zone; and, where right of way decides (not diverging lanes), to priority.
    must_yield = pending & ((foe_claim == occupied_claim) | (by_priority & (foe_claim > priority)))
    d_yield = jnp.min(jnp.where(must_yield, stop_m, jnp.inf), (1, 2))
    d_static = jnp.minimum(d_stop, d_yield)

    # IDM, whose free-road term also tracks the comfortable braking curve down to each later lane's desired
    # speed (so a vehicle enters a slower lane no faster than its limit).
    limit = town.lane_speed_limit_mps[path]
    desired = limit * state.veh_speed_frac[:, None]
    after_step_m = jnp.maximum(to_start[:, 1:] - v[:, None] * DT_S, 0.0)
    curve_mps = jnp.sqrt(desired[:, 1:] ** 2 + 2 * COMFORT_DECEL_MPS2 * after_step_m)
    free = jnp.minimum(a_max * (1 - (v / desired[:, 0]) ** 4), ((curve_mps - v[:, None]) / DT_S).min(1))
    braking = jnp.maximum(
        _idm_braking(v, a_max, gap_lead, v - v_lead), _idm_braking(v, a_max, d_static - STOP_SHORT_M + IDM_MIN_GAP_M, v)
    )
    accel = jnp.clip(free - a_max * braking, -max_decel, a_max)
    return _Plan(accel, gap_lead, d_stop, d_yield, path, limit, exit_queued, _unpack(jnp.minimum(tail, spill))[0])


def _reroute(state: WorldState, town, plan: _Plan, key):
    """Routes [N+1, ROUTE_LEN] with another exit for every vehicle that has stood REROUTE_AFTER_S at a
    queued junction mouth: a random one among its lane's successors that is empty and whose exit lane has
    room for the whole body (its rearmost body point at least the vehicle's length and IDM_MIN_GAP_M
    in). Returns (routes, re-routed [N+1]); a vehicle with no such exit keeps its route and waits on.
    """
    lane = state.veh_lane
    junction = town.lane_succ[lane]  # [N+1, MS], -1 padded
    exit_lane = town.lane_succ[jnp.maximum(junction, 0), 0]
    need_m = state.veh_box[:, 3] + IDM_MIN_GAP_M
    room = (
        (jnp.arange(junction.shape[1])[None] < town.lane_num_succ[lane][:, None])
        & jnp.isinf(plan.lane_rear_m[jnp.maximum(junction, 0)])
        & (plan.lane_rear_m[exit_lane] >= need_m[:, None])
    )
    waited = plan.exit_queued & (state.veh_standing_steps >= int(REROUTE_AFTER_S / DT_S))
    rerouted = waited & room.any(1)
    # The k-th exit with room, k uniform over how many there are.
    pick_key, *later_keys = jax.random.split(key, ROUTE_LEN - 1)
    pick = (_row_hash(pick_key, lane.shape[0]) % jnp.maximum(room.sum(1), 1).astype(jnp.uint32)).astype(jnp.int32)
    choice = jnp.argmax(room & (jnp.cumsum(room, 1) == pick[:, None] + 1), 1)
    take = lambda table: jnp.take_along_axis(table, choice[:, None], 1)[:, 0]
    new_route = [take(junction), take(exit_lane)]
    for later_key in later_keys:
        new_route.append(_pick_successor(town, new_route[-1], later_key))
    return jnp.where(rerouted[:, None], jnp.stack(new_route, 1), state.veh_route), rerouted


def step(state: WorldState, town) -> WorldState:
    """Advances one world by DT_S. Pure; N comes from the state's shapes."""
    n = state.veh_s_m.shape[0]
    idx = jnp.arange(n, dtype=jnp.int32)
    key, route_key = jax.random.split(state.key)
    v, s, lane = state.veh_speed_mps, state.veh_s_m, state.veh_lane
    plan = _plan(state, town)
    accel, path, limit = plan.accel_mps2, plan.path, plan.limit_mps
    length = town.lane_length_m[path]

    # NPCs: on the centre line, never into the leader's rear, a red stop line or a zone they yield at.
    v_new = jnp.maximum(v + accel * DT_S, 0.0)
    room = jnp.maximum(
        jnp.minimum(plan.gap_lead_m - LEADER_CLEARANCE_M, jnp.minimum(plan.d_stop_m, plan.d_yield_m)), 0.0
    )
    ds = jnp.minimum(0.5 * (v + v_new) * DT_S, room)
    v_new = jnp.where(0.5 * (v + v_new) * DT_S > room, jnp.minimum(v_new, room / DT_S), v_new)

    # The ego: clipped commands through the plant.
    ego_limit = jnp.where(s[EGO] + v[EGO] * DT_S + 0.5 > length[EGO, 0], limit[EGO, :2].min(), limit[EGO, 0])
    ego_accel = jnp.clip(
        jnp.minimum(accel[EGO], (ego_limit - v[EGO]) / DT_S), -EGO_ACCEL_LIMIT_MPS2, EGO_ACCEL_LIMIT_MPS2
    )
    ego_accel = jnp.maximum(ego_accel, -v[EGO] / DT_S)  # stop, do not reverse
    # (A key folded from the route key, as the re-routing's: the world's other draws stay as they were.)
    ego_command, ego_actuator, ego_xy, ego_yaw, ego_ds, ego_v = _drive_ego(
        state, town, ego_accel, jax.random.fold_in(route_key, 2)
    )
    ds = ds.at[EGO].set(ego_ds)
    v_new = v_new.at[EGO].set(ego_v)

    # Move along the lanes; one lane boundary at most per step (lanes are longer than a step).
    s_new = s + ds
    over = s_new > length[:, 0]
    s_new = jnp.where(over, s_new - length[:, 0], s_new)
    new_lane = jnp.where(over, path[:, 1], lane)
    extension = _pick_successor(town, state.veh_route[:, -1], route_key)
    route = jnp.where(over[:, None], jnp.concatenate([state.veh_route[:, 1:], extension[:, None]], 1), state.veh_route)
    # (A key folded from the route key: the world's other random draws stay what they were without re-routing.)
    new_route, rerouted = _reroute(state, town, plan, jax.random.fold_in(route_key, 1))
    rerouted = rerouted & ~over
    route = jnp.where(rerouted[:, None], new_route, route)
    v_new = jnp.where(idx == EGO, v_new, jnp.minimum(v_new, town.lane_speed_limit_mps[new_lane]))
    xy, yaw, _ = lane_point(town, new_lane, s_new)
    xy, yaw = xy.at[EGO].set(ego_xy), yaw.at[EGO].set(ego_yaw)
    return state._replace(
        veh_box=jnp.concatenate([xy, yaw[:, None], state.veh_box[:, 3:]], 1),
        veh_speed_mps=v_new,
        ego_action=ego_command,
        ego_actuator=ego_actuator,
        key=key,
        veh_lane=new_lane,
        veh_s_m=s_new,
        veh_prev_lane=jnp.where(over, lane, state.veh_prev_lane),
        veh_route=route,
        veh_standing_steps=jnp.where((v_new < STANDING_MPS) & ~rerouted, state.veh_standing_steps + 1, 0),
        step=state.step + 1,
    )


def hand_over_ego(state: WorldState, vehicle, town) -> WorldState:
    """The ego role passes to NPC row ``vehicle`` (int in [1, N]): rows EGO and ``vehicle`` swap their place
    on the road (centre, yaw, speed, lane, arc, previous lane, route, standing time) and their driver traits, while each row
    keeps its body (length, width, height, paint), so the ego is still the EGO_SIZE_M car, with its plant.
    Its actuators take up the NPC's motion (no acceleration, the lane's steering). The traffic goes
    on as it was; only whose sensors see it changes (a fresh viewpoint without a fresh warm-up). Bodies swap
    lengths by at most 0.9 m, i.e. 0.45 m per end, within LEADER_CLEARANCE_M: no overlap (tested).
    """
    order = jnp.arange(state.veh_s_m.shape[0]).at[EGO].set(vehicle).at[vehicle].set(EGO)
    swap = lambda a: a[order]
    return state._replace(
        ego_actuator=jnp.stack([0.0, _lane_steer(town, state.veh_lane[vehicle], state.veh_s_m[vehicle])]),
        veh_box=jnp.concatenate([state.veh_box[order, :3], state.veh_box[:, 3:]], 1),
        veh_speed_mps=swap(state.veh_speed_mps),
        veh_lane=swap(state.veh_lane),
        veh_s_m=swap(state.veh_s_m),
        veh_prev_lane=swap(state.veh_prev_lane),
        veh_route=swap(state.veh_route),
        veh_standing_steps=swap(state.veh_standing_steps),
        veh_max_accel_mps2=swap(state.veh_max_accel_mps2),
        veh_speed_frac=swap(state.veh_speed_frac),
    )


PLACE_CLEAR_M = 8.0  # place_ego moves every NPC whose centre is nearer than this off the map


def place_ego(state: WorldState, town, lane, s_m, speed_mps) -> WorldState:
    """The ego put on lane ``lane`` at arc ``s_m`` (its centre on the centre line, heading along it) at
    ``speed_mps``, to be observed, not driven on: every NPC whose centre lies within PLACE_CLEAR_M of it
    is moved far off the map (bodies never overlap the ego's), the rest of the traffic stays where it is."""
    xy, yaw, _ = lane_point(town, lane, s_m)
    near = jnp.linalg.norm(state.veh_box[:, :2] - xy, axis=-1) < PLACE_CLEAR_M
    far = jnp.where(near[:, None], jnp.float32(-1e4), state.veh_box[:, :2])
    box = jnp.concatenate([far, state.veh_box[:, 2:]], 1).at[EGO, :3].set(jnp.concatenate([xy, yaw[None]]))
    return state._replace(
        veh_box=box,
        veh_speed_mps=state.veh_speed_mps.at[EGO].set(speed_mps),
        veh_lane=state.veh_lane.at[EGO].set(lane),
        veh_s_m=state.veh_s_m.at[EGO].set(s_m),
    )


def _lane_steer(town, lane, s_m):
    """The road-wheel angle (rad) that holds a car's rear axle on lane ``lane`` at its centre's arc ``s_m``."""
    return jnp.arctan(WHEELBASE_M * lane_point(town, lane, s_m - 0.5 * WHEELBASE_M)[2])


def _drive_ego(state, town, accel, noise_key):
    """Steers the ego along its lane and moves it through its plant, asking for acceleration ``accel``.

    Returns (commands [2]: pedal, steering command rad; actuators' state [2]; new centre xy [2]; new yaw;
    arc advance along its lane m; new speed). With the exact plant (no lag, offset, gain or scale error,
    understeer or noise) this is the kinematic bicycle driven by the commands, bit for bit.
    The rear axle tracks the lane (the centre, half a wheelbase ahead, then sits on it to within a few cm;
    with a plant, within the feedback's error).
    """
    plant = state.ego_plant
    box, v, s, lane = state.veh_box[EGO], state.veh_speed_mps[EGO], state.veh_s_m[EGO], state.veh_lane[EGO]
    heading = jnp.stack([jnp.cos(box[2]), jnp.sin(box[2])])
    rear_axle = box[:2] - 0.5 * WHEELBASE_M * heading
    ref_xy, ref_yaw, ref_curv = lane_point(town, lane, s - 0.5 * WHEELBASE_M)
    offset = rear_axle - ref_xy
    lateral_m = jnp.cos(ref_yaw) * offset[1] - jnp.sin(ref_yaw) * offset[0]  # > 0: left of the lane
    curvature = ref_curv - STEER_GAIN_LATERAL * lateral_m - STEER_GAIN_HEADING * jnp.sin(wrap_angle(box[2] - ref_yaw))
    steer_command = jnp.clip(jnp.arctan(WHEELBASE_M * curvature), -EGO_STEER_LIMIT_RAD, EGO_STEER_LIMIT_RAD)
    command = jnp.stack([accel, steer_command])
    actuator = motion.lag_step(plant.lag_share, state.ego_actuator, command)
    steer = jnp.clip(plant.steer_gain * actuator[1] + plant.steer_offset_rad, -EGO_STEER_LIMIT_RAD, EGO_STEER_LIMIT_RAD)
    noise = jax.random.normal(noise_key, (2,)) * jnp.stack([plant.accel_noise_mps2, plant.curvature_noise_1pm])
    # accel >= -v / DT_S: without lag or noise only rounding is clipped here
    v_new, ds = motion.speed_step(v, plant.distance_scale * actuator[0] + noise[0])
    # Understeer: the curvature is tan(steer) / (wheelbase + K v^2), not tan(steer) / wheelbase. (where: XLA
    # divides by a traced value otherwise than by the constant, so K = 0 takes the constant's quotient.)
    dyaw = ds * jnp.tan(steer) / WHEELBASE_M
    dyaw = jnp.where(
        plant.understeer_rad_s2pm == 0.0,
        dyaw,
        dyaw / (1.0 + plant.understeer_rad_s2pm * (0.5 * (v + v_new)) ** 2 / WHEELBASE_M),
    )
    yaw_new = box[2] + dyaw + noise[1] * ds
    xy_new = centre_after(box[:2], box[2], ds, yaw_new)
    # Arc position: one Newton step of projecting the new centre onto the lane.
    guess_xy, guess_yaw, _ = lane_point(town, lane, s + ds)
    advance = ds + jnp.dot(xy_new - guess_xy, jnp.stack([jnp.cos(guess_yaw), jnp.sin(guess_yaw)]))
    pedal = accel / EGO_ACCEL_LIMIT_MPS2
    return jnp.stack([pedal, steer_command]), actuator, xy_new, wrap_angle(yaw_new), advance, v_new
