"""Traffic and ego against independent truth, on recorded trajectories of several worlds in two towns.

Overlap is an independent separating-axis test written here; road membership is read straight from the
semantic raster; red-light crossings are found from box geometry, the stop lines and ``light_states``.
"""

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import EXACT_PLANT, OPTIMISED

from e2e_percep_jax.config import DEFAULT_TOWN_SEED, WorldConfig
from e2e_percep_jax.sim import town as town_lib
from e2e_percep_jax.sim import world

HELD_OUT_SEED = 1
NUM_STEPS = 2000
NUM_WORLDS = 3
CFG = WorldConfig()
DRIVABLE = [town_lib.SEM_ROAD, town_lib.SEM_LANE_WHITE, town_lib.SEM_CENTRE_YELLOW, town_lib.SEM_STOP_LINE]
MAX_LIMIT_MPS = town_lib.ARTERIAL_SPEED_MPS


@functools.partial(jax.jit, static_argnames=("num_steps", "cfg"), compiler_options=OPTIMISED)
def _drive(keys, town, num_steps, cfg=CFG):
    states = jax.vmap(lambda k: world.reset(k, town, cfg))(keys)

    def body(states, _):
        states = jax.vmap(lambda s: world.step(s, town))(states)
        return states, states

    _, later = jax.lax.scan(body, states, None, length=num_steps)
    return jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), states, later)


def drive(town, keys, num_steps=NUM_STEPS, cfg=CFG):
    """States of len(keys) worlds from reset through ``num_steps`` steps: a WorldState of [T+1, W, ...].

    Tests share (W, num_steps) where they can: each new shape is one more compile of the whole world.
    """
    return jax.tree.map(np.asarray, _drive(keys, town, num_steps, cfg))


@pytest.fixture(scope="module", params=[DEFAULT_TOWN_SEED, HELD_OUT_SEED], ids=["default", "held_out"])
def recorded(request):
    town = town_lib.build_town(request.param)
    return jax.tree.map(np.asarray, town), drive(town, world_keys(request.param))


def world_keys(town_seed):
    return jax.random.split(jax.random.PRNGKey(100 + town_seed), NUM_WORLDS)


def corners(box):
    """Corners [..., 4, 2] of boxes [..., 5], written out here rather than taken from geometry.py."""
    c, s = np.cos(box[..., 2:3]), np.sin(box[..., 2:3])
    hl, hw = box[..., 3:4] / 2, box[..., 4:5] / 2
    x = np.stack([hl, hl, -hl, -hl], -2)[..., 0] * c - np.stack([hw, -hw, -hw, hw], -2)[..., 0] * s
    y = np.stack([hl, hl, -hl, -hl], -2)[..., 0] * s + np.stack([hw, -hw, -hw, hw], -2)[..., 0] * c
    return np.stack([x, y], -1) + box[..., None, :2]


def sat_overlap(box_a, box_b):
    """Whether boxes [M, 5] intersect with positive area: no edge normal of either separates them."""
    ca, cb = corners(box_a), corners(box_b)
    separated = np.zeros(len(box_a), bool)
    for yaw in (box_a[:, 2], box_b[:, 2]):
        for axis in (np.stack([np.cos(yaw), np.sin(yaw)], -1), np.stack([-np.sin(yaw), np.cos(yaw)], -1)):
            pa, pb = np.einsum("mcd,md->mc", ca, axis), np.einsum("mcd,md->mc", cb, axis)
            separated |= (pa.min(1) >= pb.max(1)) | (pb.min(1) >= pa.max(1))
    return ~separated


def sem_at(town, xy):
    col, row = np.moveaxis(np.floor((xy - town.map_origin_m) / town.map_res_m).astype(int), -1, 0)
    return town.sem_map[row, col]


def test_sat_finds_overlaps():
    a = np.array([[0.0, 0.0, 0.0, 4.0, 2.0]] * 4)
    b = np.array(
        [
            [3.9, 0.0, 0.0, 4.0, 2.0],
            [4.1, 0.0, 0.0, 4.0, 2.0],
            [3.0, 2.5, np.pi / 4, 4.0, 2.0],
            [3.3, 2.8, np.pi / 4, 4.0, 2.0],
        ]
    )  # the last: bounding boxes meet
    np.testing.assert_array_equal(sat_overlap(a, b), [True, False, True, False])


def assert_no_overlaps(boxes):
    """Asserts no two of each row's boxes [S, N, 5] overlap; returns how many close pairs were tested."""
    radius = 0.5 * np.hypot(boxes[..., 3], boxes[..., 4])
    i, j = np.triu_indices(boxes.shape[1], 1)
    pairs = 0
    for chunk in np.array_split(np.arange(len(boxes)), 20):  # bounding circles first, then SAT on those close
        b, r = boxes[chunk], radius[chunk]
        close = np.linalg.norm(b[:, i, :2] - b[:, j, :2], axis=-1) < r[:, i] + r[:, j]
        t, p = np.nonzero(close)
        pairs += len(t)
        hit = sat_overlap(b[t, i[p]], b[t, j[p]])
        assert not hit.any(), f"vehicles {i[p][hit][:3]} and {j[p][hit][:3]} overlap"
    return pairs


@pytest.mark.slow
def test_no_two_vehicles_ever_overlap(recorded):
    _, states = recorded
    pairs = assert_no_overlaps(states.veh_box.reshape(-1, *states.veh_box.shape[2:]))  # [T W, N, 5]
    assert pairs > 100  # the check did meet vehicles close together (queues)


@pytest.mark.slow
def test_every_corner_of_every_vehicle_stays_on_drivable_area(recorded):
    town, states = recorded
    sem = sem_at(town, corners(states.veh_box))  # [T, W, N, 4]
    off = ~np.isin(sem, DRIVABLE)
    t, w, v, _ = np.nonzero(off)
    assert not off.any(), f"{off.sum()} corners off road, e.g. step {t[:3]} world {w[:3]} vehicle {v[:3]}"


@pytest.mark.slow
def test_no_vehicle_crosses_a_stop_line_on_red(recorded):
    """A crossing is the front-centre point passing the line segment from behind to beyond during a step."""
    town, states = recorded
    box = states.veh_box
    front = box[..., :2] + 0.5 * box[..., 3:4] * np.stack([np.cos(box[..., 2]), np.sin(box[..., 2])], -1)
    ends = town.stop_line_m  # [NS, 2, 2]
    mid = ends.mean(1)
    along = ends[:, 1] - ends[:, 0]
    half_m = 0.5 * np.linalg.norm(along, axis=-1)
    along /= 2 * half_m[:, None]
    normal = np.stack([-along[:, 1], along[:, 0]], -1)  # the lane's heading at its end
    lane_end_yaw = town.lane_yaw_rad[town.stop_line_lane, np.floor(town.lane_length_m[town.stop_line_lane]).astype(int)]
    assert (np.einsum("sd,sd->s", normal, np.stack([np.cos(lane_end_yaw), np.sin(lane_end_yaw)], -1)) > 0.9).all()
    signalled = town.stop_line_light >= 0
    crossings_on_green = 0
    for w in range(box.shape[1]):
        # Each world has its own clock: [T+1, NT] light states.
        lights = np.asarray(jax.vmap(lambda t: town_lib.light_states(town, t))(states.step[:, w] * world.DT_S))
        rel_x, rel_y = front[:, w, :, None, 0] - mid[:, 0], front[:, w, :, None, 1] - mid[:, 1]  # [T+1, N, NS]
        d = rel_x * normal[:, 0] + rel_y * normal[:, 1]
        lateral = np.abs(rel_x * along[:, 0] + rel_y * along[:, 1])
        crossed = (d[:-1] < 0) & (d[1:] >= 0) & (lateral[:-1] <= half_m)
        state_before = lights[:-1][:, None, town.stop_line_light.clip(0)]  # light at the start of the step
        red = signalled & (state_before == town_lib.LIGHT_RED)
        t, v, s = np.nonzero(crossed & red)
        assert len(t) == 0, f"world {w}: vehicles {v[:3]} cross stop lines {s[:3]} on red at steps {t[:3]}"
        crossings_on_green += (crossed & signalled & (state_before == town_lib.LIGHT_GREEN)).sum()
    assert crossings_on_green > 50  # the detector does see vehicles pass lights


@pytest.mark.slow
def test_speeds_are_bounded_and_match_the_motion(recorded):
    town, states = recorded
    v = states.veh_speed_mps
    assert (v >= 0).all() and (v <= MAX_LIMIT_MPS + 1e-3).all(), v.max()
    npc_limit = town.lane_speed_limit_mps[states.veh_lane[:, :, 1:]]
    assert (v[:, :, 1:] <= npc_limit + 1e-3).all()
    moved_m = np.linalg.norm(np.diff(states.veh_box[..., :2], axis=0), axis=-1)
    assert (moved_m <= MAX_LIMIT_MPS * world.DT_S + 0.05).all(), moved_m.max()  # no jumps
    # Displacement agrees with the mean of the speeds before and after (the chord is a little shorter on curves).
    expected_m = 0.5 * (v[1:] + v[:-1]) * world.DT_S
    np.testing.assert_allclose(moved_m, expected_m, atol=0.02)
    heading_change = np.abs((np.diff(states.veh_box[..., 2], axis=0) + np.pi) % (2 * np.pi) - np.pi)
    # (+5 mrad: where two lanes join, a slow NPC's heading may turn a few mrad more than the radius allows)
    assert (heading_change <= moved_m / town_lib.MIN_TURN_RADIUS_M * 1.3 + 5e-3).all()


@pytest.mark.slow
def test_traffic_keeps_moving(recorded):
    _, states = recorded
    window = 100  # 10 s
    xy = states.veh_box[..., :2]
    for t0 in range(0, NUM_STEPS - window + 1, window):
        moved = np.linalg.norm(xy[t0 + window] - xy[t0], axis=-1) > 1.0  # [W, N]
        assert (moved.mean(-1) > 0.4).all(), (t0, moved.mean(-1))
    assert states.veh_speed_mps[NUM_STEPS // 2 :].mean() > 2.0


@pytest.mark.slow
def test_ego_commands_are_within_limits_and_the_plant_is_what_moved_the_ego(recorded):
    """The plant written out here in NumPy from its hidden parameters: the actuators follow the commands
    by the lag's share exactly, and speed and curvature follow the actuators up to the plant's per-step noise,
    whose spread they show."""
    _, states = recorded
    pedal, steer_cmd = states.ego_action[1:, :, 0], states.ego_action[1:, :, 1]
    assert (np.abs(pedal) <= 1.0 + 1e-6).all() and (np.abs(steer_cmd) <= world.EGO_STEER_LIMIT_RAD + 1e-6).all()
    assert np.abs(steer_cmd).max() > 0.05 and pedal.min() < -0.2 and pedal.max() > 0.2  # it does steer and brake
    plant = jax.tree.map(lambda a: a[0], states.ego_plant)  # [W] each: drawn once per drive
    np.testing.assert_array_equal(states.ego_plant.steer_gain, np.broadcast_to(plant.steer_gain, states.step.shape))
    assert np.ptp(plant.steer_offset_rad) > 0 and np.ptp(plant.distance_scale) > 0  # drawn per drive
    command = np.stack([pedal * world.EGO_ACCEL_LIMIT_MPS2, steer_cmd], -1)
    act = states.ego_actuator
    share = plant.lag_share[:, None]
    np.testing.assert_allclose(act[1:], act[:-1] + share * (command - act[:-1]), atol=1e-5)
    v = states.veh_speed_mps[:, :, world.EGO]
    moving = v[1:] > 0.5  # (a standing car's speed is clipped at 0)
    accel_residual = ((v[1:] - v[:-1]) / world.DT_S - plant.distance_scale * act[1:, :, 0])[moving]
    assert abs(accel_residual.std() / CFG.ego_accel_noise_mps2 - 1) < 0.1
    ds = 0.5 * (v[1:] + v[:-1]) * world.DT_S
    wheel = np.clip(
        plant.steer_gain * act[1:, :, 1] + plant.steer_offset_rad, -world.EGO_STEER_LIMIT_RAD, world.EGO_STEER_LIMIT_RAD
    )
    curvature = np.tan(wheel) / (world.WHEELBASE_M + plant.understeer_rad_s2pm * (0.5 * (v[1:] + v[:-1])) ** 2)
    dyaw = (np.diff(states.veh_box[:, :, world.EGO, 2], axis=0) + np.pi) % (2 * np.pi) - np.pi
    curvature_residual = dyaw[moving] / ds[moving] - curvature[moving]
    assert abs(curvature_residual.std() / CFG.ego_curvature_noise_1pm - 1) < 0.1


def test_an_exact_plant_reproduces_the_recorded_drive_of_the_exact_action_world():
    """tests/data/exact_world_drive.npz: two worlds of town 0 with 20 NPCs, reset from PRNGKey(7) and driven
    400 steps by the world before it had a plant (its actions then were acceleration m/s^2 and steering rad).
    All of the plant's fields at zero drive them again bit for bit. (Compiled at XLA's default optimisation,
    as the recording was: the suite's lower level moves rounding.)"""
    recorded = np.load(os.path.join(os.path.dirname(__file__), "data", "exact_world_drive.npz"))
    cfg = WorldConfig(num_vehicles=20, **EXACT_PLANT)
    states = drive(town_lib.build_town(DEFAULT_TOWN_SEED), jax.random.split(jax.random.PRNGKey(7), 2), 400, cfg)
    boxes, ego_speed, command = states.veh_box[1:], states.veh_speed_mps[1:, :, world.EGO], states.ego_action[1:]
    np.testing.assert_array_equal(boxes[:, :, world.EGO], recorded["ego_box"])
    np.testing.assert_array_equal(boxes[-1], recorded["final_boxes"])
    np.testing.assert_array_equal(ego_speed, recorded["ego_speed_mps"])
    np.testing.assert_array_equal(command[..., 1], recorded["ego_accel_steer"][..., 1])
    np.testing.assert_allclose(
        command[..., 0] * world.EGO_ACCEL_LIMIT_MPS2, recorded["ego_accel_steer"][..., 0], rtol=0, atol=1e-6
    )  # the pedal: the acceleration over its limit


@pytest.mark.slow
def test_ego_hand_overs_keep_bodies_apart_on_the_road_and_the_ego_within_its_limits():
    """The ego role passed to a random NPC every 11 steps (batches_per_drive > 1), 40 hand-overs in each
    of three worlds: no two bodies overlap and every corner stays on the road, right after each swap of
    places between bodies of different lengths and in the steps after it; the ego keeps its size and its
    action limits, and the ego's position jumps only at hand-overs (the swap does happen)."""
    town = town_lib.build_town(DEFAULT_TOWN_SEED)
    segments, seg_len, n = 40, 11, CFG.num_vehicles + 1

    @jax.jit
    def drive_handing_over(keys, town):
        step = jax.vmap(lambda x: world.step(x, town))
        states = jax.vmap(lambda k: world.reset(k, town, CFG))(keys)
        states = jax.lax.fori_loop(0, 200, lambda _, s: step(s), states)

        def segment(states, key):
            states = jax.vmap(world.hand_over_ego, in_axes=(0, 0, None))(
                states, jax.random.randint(key, (len(keys),), 1, n), town
            )
            last, later = jax.lax.scan(lambda s, _: (step(s),) * 2, states, None, length=seg_len)
            return last, jax.tree.map(lambda a, b: jnp.concatenate([a[None], b[:-1]]), states, later)

        return jax.lax.scan(segment, states, jax.random.split(keys[0], segments))[1]

    states = jax.tree.map(np.asarray, drive_handing_over(world_keys(DEFAULT_TOWN_SEED), town))
    box = states.veh_box.reshape(-1, n, 5)  # [segments seg_len W, N+1, 5]: every state, hand-overs first
    np.testing.assert_allclose(box[:, world.EGO, 3:], np.broadcast_to(world.EGO_SIZE_M[:2], (len(box), 2)))
    assert assert_no_overlaps(box) > 100
    assert np.isin(sem_at(jax.tree.map(np.asarray, town), corners(box)), DRIVABLE).all()
    assert (np.abs(states.ego_action) <= [1.0 + 1e-6, world.EGO_STEER_LIMIT_RAD + 1e-6]).all()
    ego_xy = states.veh_box[..., world.EGO, :2]  # [segments, seg_len, W, 2]
    step_m = np.linalg.norm(np.diff(ego_xy, axis=1), axis=-1)
    jump_m = np.linalg.norm(ego_xy[1:, 0] - ego_xy[:-1, -1], axis=-1)  # across each hand-over
    assert step_m.max() <= MAX_LIMIT_MPS * world.DT_S + 0.05 and np.median(jump_m) > 20.0


@pytest.fixture(scope="module")
def town0():
    return town_lib.build_town(DEFAULT_TOWN_SEED)


@pytest.mark.slow
def test_same_key_is_bit_identical_and_other_keys_differ(town0):
    keys = jnp.stack([jax.random.PRNGKey(5), jax.random.PRNGKey(5), jax.random.PRNGKey(6)])
    last = jax.tree.map(lambda a: a[-1], drive(town0, keys))
    for leaf in jax.tree.leaves(last):
        np.testing.assert_array_equal(leaf[0], leaf[1])
    assert not np.array_equal(last.veh_box[0], last.veh_box[2])
    again = jax.tree.map(lambda a: a[-1], drive(town0, keys[::-1]))  # another run, worlds in another order
    for a, b in zip(jax.tree.leaves(last), jax.tree.leaves(again)):
        np.testing.assert_array_equal(a[0], b[1])


def _assert_states_close(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        x, y = np.asarray(x), np.asarray(y)
        if np.issubdtype(x.dtype, np.floating):
            np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-4)
        else:
            np.testing.assert_array_equal(x, y)


_jit_step = jax.jit(world.step)
_jit_reset = jax.jit(world.reset, static_argnums=2)


@pytest.mark.slow
def test_jit_equals_no_jit(town0):
    states = drive(town0, world_keys(DEFAULT_TOWN_SEED))  # the recorded worlds (a compile-cache hit)
    state = jax.tree.map(lambda a: jnp.asarray(a[300, 0]), states)  # warmed up: queues, lights, junctions
    jitted, eager = state, state
    for _ in range(2):
        jitted, eager = _jit_step(jitted, town0), world.step(eager, town0)
    _assert_states_close(jitted, eager)  # (eager reset is not compared: op-by-op it costs ~10 s for little)


@pytest.mark.slow
def test_vmap_over_worlds_equals_a_python_loop(town0):
    keys = world_keys(DEFAULT_TOWN_SEED)
    batched = drive(town0, keys)  # the recorded worlds (a compile-cache hit)
    for w, key in enumerate(keys):  # one world at a time, by the jitted single-world step
        state = _jit_reset(key, town0, CFG)
        for t in range(100):  # compared early, before float rounding differences could grow along the drive
            _assert_states_close(jax.tree.map(lambda a: a[t, w], batched), state)
            state = _jit_step(state, town0)


@pytest.mark.slow
def test_no_gridlock_in_a_15000_step_drive(town0):
    """The fraction of vehicles that move at all in every 10 s window of a 25-minute drive stays high."""
    window, num_windows = 100, 150

    @functools.partial(jax.jit, compiler_options=OPTIMISED)
    def fractions(keys, town):  # the town as an argument, not a closed-over constant: faster to compile
        def one_window(states, _):
            def body(carry, _):
                states, moved = carry
                states = jax.vmap(lambda s: world.step(s, town))(states)
                return (states, moved | (states.veh_speed_mps > 0.1)), None

            moved = jnp.zeros(states.veh_speed_mps.shape, bool)
            (states, moved), _ = jax.lax.scan(body, (states, moved), None, length=window)
            return states, moved.mean(-1)

        states = jax.vmap(lambda k: world.reset(k, town, CFG))(keys)
        return jax.lax.scan(one_window, states, None, length=num_windows)[1]

    moving = np.asarray(fractions(jax.random.split(jax.random.PRNGKey(21), 2), town0))  # [windows, worlds]
    assert moving.min() > 0.4, moving.min(0)
    assert moving[-10:].mean() > 0.6, moving[-10:].mean(0)


GRIDLOCK_STATE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "gridlock_town0.npz")


def _moving_and_boxes(state, town, num_steps):
    """(share of vehicles moving per 10 s window [num_steps / 100], boxes of every step [num_steps, N+1, 5])."""

    @jax.jit  # traced afresh on every call: it reads world.REROUTE_AFTER_S as it is now
    def run(state, town):
        def body(state, _):
            state = world.step(state, town)
            return state, (state.veh_speed_mps > 0.1, state.veh_box)

        return jax.lax.scan(body, state, None, length=num_steps)[1]

    moving, boxes = jax.tree.map(np.asarray, run(state, town))
    return moving.reshape(-1, 100, moving.shape[-1]).any(1).mean(-1), boxes


@pytest.mark.slow
def test_a_ring_of_full_roads_clears_when_vehicles_take_other_exits(town0, monkeypatch):
    """A gridlock of town 0 (``PRNGKey(7)``, 100 vehicles, 930,000 steps into the drive, recorded before
    re-routing existed): 27 vehicles wait at junction mouths whose exits are queued and every other one
    queues behind them. Without re-routing nobody moves in 300 s; with it the ring clears once the heads
    have stood REROUTE_AFTER_S, with bodies apart and on the road."""
    saved = np.load(GRIDLOCK_STATE)
    # (saved before the ego had a plant: it drives with the exact one)
    state = world.WorldState(
        **{name: jnp.asarray(saved[name]) for name in saved.files},
        ego_actuator=jnp.zeros(2),
        ego_plant=world.draw_plant(jax.random.PRNGKey(0), WorldConfig(**EXACT_PLANT)),
    )
    plan = world._plan(state, town0)
    assert int(plan.exit_queued.sum()) == 27 and int((state.veh_speed_mps < world.STANDING_MPS).sum()) >= 100

    with monkeypatch.context() as patched:
        patched.setattr(world, "REROUTE_AFTER_S", 1e8)
        stuck, _ = _moving_and_boxes(state, town0, 3000)
    assert stuck.max() <= 0.01, stuck.max()  # at most one vehicle (of 101) moves at all

    moving, boxes = _moving_and_boxes(state, town0, 3000)
    heads_wait = int(world.REROUTE_AFTER_S / world.DT_S) // 100
    assert moving[:heads_wait].max() <= 0.01, moving[:heads_wait]  # nothing changes before the heads re-route
    # Then the traffic flows and keeps flowing (measured: every window 0.31-0.70 moving, 0.52 on average).
    assert moving[heads_wait + 1 :].min() > 0.25 and moving[heads_wait + 1 :].mean() > 0.4, moving
    assert_no_overlaps(boxes)
    assert np.isin(sem_at(jax.tree.map(np.asarray, town0), corners(boxes)), DRIVABLE).all()
