"""The pose belief (e2e_percep_jax/pose_belief.py): soft targets, mode + offset decoding, the histogram
filter against brute-force Bayes (motion through a motion model with lag and process noise, or by the lidar
odometry from a uniform or a known start, relocation, measurement, restarts), its credible regions against
sorting, the known-start odometry against a NumPy integration of the motion model, and the filter on real
drives of a world whose ego has a plant.

The expectations are computed here in NumPy float64 from the motion model's equations as
e2e_percep_jax/sim/motion.py's docstring states them; pose_belief's and motion.py's functions only produce the
values under test (the lidar odometry's poses and covariances come from ``ego_motion.follow``, tested in
test_ego_motion.py)."""

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import EXACT_PLANT, OPTIMISED, np_region_share, odometry_model, street

from e2e_percep_jax import calibration, config, ego_motion, pose_belief
from e2e_percep_jax.sim import motion as motion_lib
from e2e_percep_jax.sim import rollout, world
from e2e_percep_jax.sim.motion import MotionModel

GRID = pose_belief.Grid(cell_m=10.0, heading_bins=36)
DT_S, WHEELBASE_M = 0.1, 2.7  # the world's step and wheelbase, written out again
# A motion model unlike the exact bicycle in every field (its process noise is irrelevant to a point odometry).
LAGGED = MotionModel(
    lag_share=0.45,
    accel_per_pedal_mps2=2.6,
    accel_bias_mps2=-0.08,
    steer_gain=1.15,
    steer_bias=0.012,
    understeer_s2pm2=-0.0015,
    heading_noise_rad2pm=0.002,
    position_noise_m2pm=0.3,
)


def random_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    yaw = rng.uniform(-np.pi, np.pi, n)
    return np.stack(
        [rng.uniform(0, 420, n), rng.uniform(0, 420, n), np.cos(yaw), np.sin(yaw), rng.uniform(0, 12, n)], -1
    ).astype(np.float32)


def head_naming(pose, grid):
    """A belief head that names ``pose`` exactly: log soft targets, and the true offsets in every cell / bin."""
    cell, offset = pose_belief.true_cell(pose[:, :2], grid)
    k, heading_offset = pose_belief.true_bin(jnp.arctan2(pose[:, 3], pose[:, 2]), grid)
    return {
        "place_logit": jnp.log(pose_belief.place_target(pose[:, :2], grid)),
        "place_offset": jnp.broadcast_to(offset[:, None, :], (len(pose), grid.num_cells, 2)),
        "heading_logit": jnp.log(pose_belief.heading_target(jnp.arctan2(pose[:, 3], pose[:, 2]), grid)),
        "heading_offset": jnp.broadcast_to(heading_offset[:, None], (len(pose), grid.heading_bins)),
        "speed": pose[:, 4] / pose_belief.SPEED_SCALE_MPS,
    }


def blank_head(batch, grid, speed_mps):
    """A head that carries no place or heading information (all logits equal), with the given speed."""
    g, h = grid.num_cells, grid.heading_bins
    return {
        "place_logit": jnp.zeros((batch, g)),
        "place_offset": jnp.zeros((batch, g, 2)),
        "heading_logit": jnp.zeros((batch, h)),
        "heading_offset": jnp.zeros((batch, h)),
        "speed": jnp.asarray(speed_mps, jnp.float32) / pose_belief.SPEED_SCALE_MPS,
    }


def softmax(x):
    x = np.asarray(x, np.float64)
    e = np.exp(x - x.max())
    return e / e.sum()


def np_measurement(place_logit, heading_logit, floor, n, h):
    """The head's place and heading probabilities, each mixed with ``floor`` of uniform mass, as a product
    over (heading bin, row, column) [h, n, n], float64 (before the power)."""
    place = (1 - floor) * softmax(place_logit) + floor / (n * n)
    heading = (1 - floor) * softmax(heading_logit) + floor / h
    return heading[:, None, None] * place.reshape(n, n)[None]


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# ----------------------------------------------------------------------------- the motion model in NumPy


def np_model_step(model, actuator, command, speed_mps):
    """One step of the motion model as motion.py's docstring states it, float64: (actuators after [2],
    speed after, distance m, yaw change rad)."""
    actuator = np.asarray(actuator, np.float64) + model.lag_share * (np.asarray(command, np.float64) - actuator)
    v_new = max(speed_mps + (model.accel_per_pedal_mps2 * actuator[0] + model.accel_bias_mps2) * DT_S, 0.0)
    ds = 0.5 * (speed_mps + v_new) * DT_S
    tan, v_mid = math.tan(actuator[1]), 0.5 * (speed_mps + v_new)
    kappa = (model.steer_gain * tan + model.steer_bias + model.understeer_s2pm2 * tan * v_mid**2) / WHEELBASE_M
    return actuator, v_new, ds, ds * kappa


def np_centre_move(ds, dyaw, yaw):
    """Displacement [..., 2] of the centre of cars at headings ``yaw`` [...]: the rear axle (half a
    wheelbase behind the centre) drives ``ds`` along the mid-step heading."""
    unit = lambda a: np.stack([np.cos(a), np.sin(a)], -1)
    rear = -0.5 * WHEELBASE_M * unit(yaw) + ds * unit(yaw + 0.5 * dyaw)
    return rear + 0.5 * WHEELBASE_M * unit(yaw + dyaw)


def np_odometry(model, start, commands):
    """The motion model integrated from pose ``start`` [5] (x, y, cos, sin, speed) by ``commands`` [T, 2],
    the actuators starting at the first command (steady state): poses [T+1, 5] and actuators [T, 2]."""
    x, y, yaw, v = start[0], start[1], math.atan2(start[3], start[2]), start[4]
    actuator = np.asarray(commands[0], np.float64)
    poses, actuators = [(x, y, yaw, v)], []
    for command in commands:
        actuator, v_new, ds, dyaw = np_model_step(model, actuator, command, v)
        dx, dy = np_centre_move(ds, dyaw, yaw)
        x, y, yaw, v = x + dx, y + dy, yaw + dyaw, v_new
        poses.append((x, y, yaw, v))
        actuators.append(actuator)
    p = np.array(poses)
    return np.stack([p[:, 0], p[:, 1], np.cos(p[:, 2]), np.sin(p[:, 2]), p[:, 3]], -1), np.array(actuators)


# ----------------------------------------------------------------------------- targets and decoding


def test_soft_targets_sum_to_one_and_peak_at_the_true_cell_and_bin():
    pose = random_poses(200)
    place = np.asarray(pose_belief.place_target(pose[:, :2], GRID))
    yaw = np.arctan2(pose[:, 3], pose[:, 2])
    heading = np.asarray(pose_belief.heading_target(jnp.asarray(yaw), GRID))
    np.testing.assert_allclose(place.sum(-1), 1.0, rtol=1e-5)
    np.testing.assert_allclose(heading.sum(-1), 1.0, rtol=1e-5)
    # The true cell and bin by hand: 10 m cells from -30 m, row-major (i along y); 10-degree bins from -pi.
    want_cell = np.floor((pose[:, 1] + 30) / 10) * 48 + np.floor((pose[:, 0] + 30) / 10)
    np.testing.assert_array_equal(place.argmax(-1), want_cell)
    np.testing.assert_array_equal(heading.argmax(-1), np.floor((yaw + np.pi) / (np.pi / 18)) % 36)


@pytest.mark.parametrize("std_cells", [1.0, 1.5])
def test_soft_targets_have_the_configured_width(std_cells):
    """Label smoothing (``--model.pose_target_std_cells``): a Gaussian sampled at unit spacing has the
    continuous one's mean and variance up to exp(-2 pi^2 std^2) (Poisson summation), so for poses away from
    the grid's edge the place target's mean is the true point and its variance (std x cell)^2 per axis, and
    the heading target's mean offset is zero and its variance (std x bin)^2."""
    grid = dataclasses.replace(GRID, target_std_cells=std_cells)
    rng = np.random.default_rng(4)
    xy = rng.uniform(100.0, 300.0, (50, 2))
    yaw = rng.uniform(-np.pi, np.pi, 50)
    place = np.asarray(pose_belief.place_target(jnp.asarray(xy), grid), np.float64)
    d = np.asarray(grid.cell_centres())[None] - xy[:, None]  # [50, G, 2] cell centre minus the point
    np.testing.assert_allclose(np.einsum("pg,pgk->pk", place, d), 0.0, atol=1e-3 * grid.cell_m)
    np.testing.assert_allclose(np.einsum("pg,pgk->pk", place, d**2), (std_cells * grid.cell_m) ** 2, rtol=1e-3)
    heading = np.asarray(pose_belief.heading_target(jnp.asarray(yaw), grid), np.float64)
    a = (np.asarray(grid.bin_centres())[None] - yaw[:, None] + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(np.sum(heading * a, -1), 0.0, atol=1e-3 * grid.bin_rad)
    np.testing.assert_allclose(np.sum(heading * a**2, -1), (std_cells * grid.bin_rad) ** 2, rtol=1e-3)


def test_mode_and_offset_decoding_round_trips_a_pose():
    pose = random_poses(200, seed=1)
    got = np.asarray(pose_belief.decode(head_naming(jnp.asarray(pose), GRID), GRID))
    np.testing.assert_allclose(got, pose, atol=1e-4)  # float32 metres of a 480 m area


# ----------------------------------------------------------------------------- the filter against brute force


@pytest.mark.slow
def test_measurement_update_is_bayes_rule_against_brute_force():
    """A tiny grid (40 m cells: 12 x 12, 4 headings), a random prior and random head outputs, no motion
    (standing, zero commands): the filter's posterior equals (prior with the relocation share of each cell
    spread over its headings) x floored likelihood tempered by the power times the standing share,
    normalised, cell by cell."""
    grid = pose_belief.Grid(cell_m=40.0, heading_bins=4)
    rng = np.random.default_rng(2)
    b, h, n = 2, grid.heading_bins, grid.n
    prior = rng.uniform(0.0, 1.0, (b, h, n, n))
    prior /= prior.sum(axis=(1, 2, 3), keepdims=True)
    head = {
        "place_logit": rng.normal(0, 2, (b, n * n)),
        "heading_logit": rng.normal(0, 2, (b, h)),
        "place_offset": np.zeros((b, n * n, 2)),
        "heading_offset": np.zeros((b, h)),
        "speed": np.zeros(b),
    }
    state = pose_belief.init_state(b, grid).replace(belief=jnp.asarray(prior, jnp.float32))
    f32 = {k: jnp.asarray(v, jnp.float32) for k, v in head.items()}
    floor, power, relocation, standing = 0.1, 0.7, 0.01, 0.3
    new, _ = pose_belief.filter_step(
        state,
        f32,
        jnp.zeros((b, 2)),
        jnp.zeros(b, bool),
        grid,
        MotionModel(),
        floor=floor,
        power=power,
        relocation=relocation,
        full_measure_m=2.0,
        stopped_share=standing,
    )
    for row in range(b):
        place = (1 - floor) * softmax(head["place_logit"][row]) + floor / (n * n)
        heading = (1 - floor) * softmax(head["heading_logit"][row]) + floor / h
        want = np.zeros((h, n, n))
        for k in range(h):
            for i in range(n):
                for j in range(n):
                    mixed = (1 - relocation) * prior[row, k, i, j] + relocation * prior[row, :, i, j].mean()
                    want[k, i, j] = mixed * (place[i * n + j] * heading[k]) ** (power * standing)
        np.testing.assert_allclose(new.belief[row], want / want.sum(), rtol=1e-4, atol=1e-9)


def np_transition(move_m, ds_m, yaw_after_rad, model, n, cell_m, h, relocation, heading_var_rad2, stats):
    """The histogram's motion step as a dense matrix [S, S] (S = h n n, state (k, i, j) at (k n + i) n + j,
    i along y, j along x), built from where each source state's mass goes, stage by stage: bin k's mass
    split bilinearly by its displacement ``move_m[k]`` (x, then y; mass leaving the grid lost), position
    noise (per axis, the variance the split has not spread), heading noise (``heading_var_rad2``, to the
    neighbouring bins, around), whole bins of ``yaw_after_rad`` rolled onto
    the heading axis, then ``relocation`` of each cell's mass spread evenly over its headings."""
    s = h * n * n
    index = lambda k, i, j: (k * n + i) * n + j
    bin_rad = 2 * np.pi / h

    def stage(where):
        """Matrix of a stage: where(k, i, j) lists (k', i', j', share) for the mass of (k, i, j)."""
        m = np.zeros((s, s))
        for k in range(h):
            for i in range(n):
                for j in range(n):
                    for k2, i2, j2, share in where(k, i, j):
                        if 0 <= i2 < n and 0 <= j2 < n:  # off the grid: lost
                            m[index(k2 % h, i2, j2), index(k, i, j)] += share
        return m

    shift = np.clip(np.asarray(move_m) / cell_m, -1.0, 1.0)  # [h, 2] cells (x, y)
    step = lambda u: 1 if u > 0 else -1
    split_x = stage(lambda k, i, j: [(k, i, j, 1 - abs(shift[k, 0])), (k, i, j + step(shift[k, 0]), abs(shift[k, 0]))])
    split_y = stage(lambda k, i, j: [(k, i, j, 1 - abs(shift[k, 1])), (k, i + step(shift[k, 1]), j, abs(shift[k, 1]))])
    variance = model.position_noise_m2pm * ds_m / cell_m**2
    missing = np.maximum(variance - np.abs(shift) * (1 - np.abs(shift)), 0.0)  # [h, 2]
    pos_share = np.minimum(0.5 * missing, 0.25)
    noise_x = stage(
        lambda k, i, j: [
            (k, i, j, 1 - 2 * pos_share[k, 0]),
            (k, i, j - 1, pos_share[k, 0]),
            (k, i, j + 1, pos_share[k, 0]),
        ]
    )
    noise_y = stage(
        lambda k, i, j: [
            (k, i, j, 1 - 2 * pos_share[k, 1]),
            (k, i - 1, j, pos_share[k, 1]),
            (k, i + 1, j, pos_share[k, 1]),
        ]
    )
    head_share = min(0.5 * heading_var_rad2 / bin_rad**2, 0.25)
    noise_heading = stage(
        lambda k, i, j: [(k, i, j, 1 - 2 * head_share), (k - 1, i, j, head_share), (k + 1, i, j, head_share)]
    )
    whole = int(np.round(yaw_after_rad / bin_rad))
    roll = stage(lambda k, i, j: [(k + whole, i, j, 1.0)])
    relocate = stage(lambda k, i, j: [(k, i, j, 1 - relocation)] + [(k2, i, j, relocation / h) for k2 in range(h)])
    stats["rolls"].add(whole)
    stats["position_diffused"] |= bool(np.any(missing > 0))
    stats["split_covers"] |= bool(np.any(missing == 0))
    stats["capped"] |= head_share == 0.25 or bool(np.any(pos_share == 0.25))
    return relocate @ roll @ noise_heading @ noise_y @ noise_x @ split_y @ split_x


MOVING_MODELS = {
    "lagged_with_noise": dict(
        lag_share=0.6,
        accel_per_pedal_mps2=2.5,
        accel_bias_mps2=-0.1,
        steer_gain=1.3,
        steer_bias=0.02,
        understeer_s2pm2=-0.001,
        heading_noise_rad2pm=0.05,
        position_noise_m2pm=1.0,
    ),
    # noise large enough that both shares reach their cap of 0.25
    "saturated_noise": dict(
        lag_share=0.3,
        accel_per_pedal_mps2=3.5,
        accel_bias_mps2=0.2,
        steer_gain=0.9,
        steer_bias=-0.03,
        understeer_s2pm2=0.002,
        heading_noise_rad2pm=3.0,
        position_noise_m2pm=30.0,
    ),
}


@pytest.mark.parametrize("name", sorted(MOVING_MODELS))
def test_filter_step_is_brute_force_bayes_through_the_motion_model(name, monkeypatch):
    """10 frames of 2 streams on a 6 x 6 grid of 2 m cells with 8 headings, driven at 8-12 m/s with
    steering left (row 0) and right (row 1), random head outputs every frame, row 1 restarting at frame 3.
    Every frame, the filter's belief, speed track, heading offset and actuators equal a float64 brute force:
    the NumPy motion model, the dense transition matrix of :func:`np_transition`, the floored likelihood
    tempered by the power times the frame's share (the distance driven over ``full_measure_m``, at most 1, 1 on
    a drive's first frame), normalised; a restarting row starts from the uniform prior and the head's speed, its
    actuators then taking the next frame's commands as their steady state."""
    monkeypatch.setattr(pose_belief, "AREA_ORIGIN_M", 0.0)
    monkeypatch.setattr(pose_belief, "AREA_SIZE_M", 12.0)
    grid = pose_belief.Grid(cell_m=2.0, heading_bins=8)
    n, h, b, frames = grid.n, grid.heading_bins, 2, 10
    assert n == 6
    model = MotionModel(**MOVING_MODELS[name])
    floor, power, gain, relocation, heading_scale = 0.08, 0.6, 0.3, 0.02, 2.5
    full_measure_m, standing = 1.0, 0.5  # frames drive 0.8-1.2 m: some count in full, some in part
    rng = np.random.default_rng(11)
    first = np.zeros((frames, b), bool)
    first[0] = True
    first[3, 1] = True
    pedal = rng.uniform(-0.6, 0.8, (frames, b))
    steer = np.stack([rng.uniform(0.2, 0.3, frames), rng.uniform(-0.3, -0.2, frames)], -1)
    commands = np.stack([pedal, steer], -1).astype(np.float32)  # [frames, b, 2]: frame t's prev_action
    heads = [
        {
            "place_logit": rng.normal(0, 1.5, (b, n * n)),
            "heading_logit": rng.normal(0, 1.5, (b, h)),
            "place_offset": rng.uniform(-0.5, 0.5, (b, n * n, 2)),
            "heading_offset": rng.uniform(-0.5, 0.5, (b, h)),
            "speed": rng.uniform(0.8, 1.2, b),
        }
        for _ in range(frames)
    ]
    heads = [{k: v.astype(np.float32) for k, v in head.items()} for head in heads]

    step = jax.jit(
        lambda state, head, action, first: pose_belief.filter_step(
            state,
            head,
            action,
            first,
            grid,
            model,
            floor=floor,
            power=power,
            speed_gain=gain,
            relocation=relocation,
            heading_noise_scale=heading_scale,
            full_measure_m=full_measure_m,
            stopped_share=standing,
        )
    )
    state = pose_belief.init_state(b, grid)
    centres = -np.pi + (np.arange(h) + 0.5) * 2 * np.pi / h
    want = [
        dict(
            belief=np.full((h, n, n), 1.0 / (h * n * n)),
            speed=0.0,
            offset=0.0,
            actuator=np.zeros(2),
            actuator_set=False,
        )
        for _ in range(b)
    ]
    stats = {"rolls": set(), "position_diffused": False, "split_covers": False, "capped": False, "shares": set()}
    for t in range(frames):
        state, pose = step(state, heads[t], jnp.asarray(commands[t]), jnp.asarray(first[t]))
        for row in range(b):
            w, head, command = want[row], {k: np.float64(v[row]) for k, v in heads[t].items()}, commands[t, row]
            head_speed = 10.0 * head["speed"]
            if first[t, row]:
                w.update(
                    belief=np.ones((h, n, n)), speed=head_speed, offset=0.0, actuator=np.zeros(2), actuator_set=False
                )
                share = 1.0
            else:
                actuator = w["actuator"] if w["actuator_set"] else command.astype(np.float64)
                actuator, v_new, ds, dyaw = np_model_step(model, actuator, command, w["speed"])
                move = np_centre_move(ds, dyaw, centres + w["offset"])
                yaw_after = w["offset"] + dyaw
                heading_var = heading_scale * model.heading_noise_rad2pm * ds
                matrix = np_transition(move, ds, yaw_after, model, n, grid.cell_m, h, relocation, heading_var, stats)
                whole = np.round(yaw_after / grid.bin_rad)
                share = max(min(ds / full_measure_m, 1.0), standing)
                w.update(
                    belief=(matrix @ w["belief"].ravel()).reshape(h, n, n),
                    speed=v_new + gain * (head_speed - v_new),
                    offset=yaw_after - whole * grid.bin_rad,
                    actuator=actuator,
                    actuator_set=True,
                )
            measured = np_measurement(head["place_logit"], head["heading_logit"], floor, n, h)
            posterior = w["belief"] * measured ** (power * share)
            w["belief"] = posterior / posterior.sum()
            stats["shares"].add("full" if share == 1.0 else "part")
            where = f"frame {t} row {row}"
            np.testing.assert_allclose(state.belief[row], w["belief"], rtol=2e-4, atol=1e-8, err_msg=where)
            np.testing.assert_allclose(state.speed_mps[row], w["speed"], rtol=1e-5, err_msg=where)
            np.testing.assert_allclose(pose[row, 4], w["speed"], rtol=1e-5, err_msg=where)
            np.testing.assert_allclose(state.yaw_offset_rad[row], w["offset"], atol=1e-5, err_msg=where)
            np.testing.assert_allclose(state.actuator[row], w["actuator"], atol=1e-6, err_msg=where)
            assert bool(state.actuator_set[row]) == w["actuator_set"], where
    # the test exercised what it claims: rolls both ways, the split's spread both short of and above the noise
    assert {-1, 1} <= stats["rolls"], stats
    assert stats["position_diffused"]
    assert stats["shares"] == {"full", "part"}, stats
    assert stats["capped"] == (name == "saturated_noise")
    if name == "lagged_with_noise":
        assert stats["split_covers"]


@pytest.mark.parametrize("known_start", [False, True])
def test_filter_step_moved_by_the_lidar_odometry_is_brute_force_bayes(known_start, monkeypatch):
    """7 frames of one stream down a curving street of buildings (``helpers.street``; the commands steer
    the same curve), on a 6 x 6 grid of 2 m cells with 8 headings, random head outputs every frame, the scans
    given. Every frame the belief and speed track equal a float64 brute force: each frame's motion the lidar
    odometry's (``ego_motion.follow``'s poses from the same start, differenced here: the chord in the car's
    axes turned to each bin's heading), the dense transition of :func:`np_transition`, its heading variance
    the motion model's times the scale from a uniform start, or from a known start what the odometry's
    heading variance grew in the frame (``follow``'s covariances; none where it fell), then the tempered
    likelihood."""
    monkeypatch.setattr(pose_belief, "AREA_ORIGIN_M", 0.0)
    monkeypatch.setattr(pose_belief, "AREA_SIZE_M", 12.0)
    grid = pose_belief.Grid(cell_m=2.0, heading_bins=8)
    n, h, frames = grid.n, grid.heading_bins, 7
    model = odometry_model(heading_noise_rad2pm=0.05, position_noise_m2pm=1.0, yaw_noise_rad2pm=0.02)
    assert ego_motion.uses_scans(model)
    floor, power, gain, relocation, heading_scale, full_measure_m, standing = 0.08, 0.6, 0.3, 0.02, 2.5, 1.5, 0.5
    _, _, scans = street(np.full(frames - 1, 1.0), np.full(frames - 1, 0.1))  # 10 m/s, curving left
    commands = np.zeros((frames, 1, 2), np.float32)  # frame t's prev_action: the pedal at 0, steering the curve
    commands[..., 1] = math.atan(0.1 * WHEELBASE_M)
    rng = np.random.default_rng(12)
    heads = [
        {
            "place_logit": rng.normal(0, 1.5, (1, n * n)),
            "heading_logit": rng.normal(0, 1.5, (1, h)),
            "place_offset": rng.uniform(-0.5, 0.5, (1, n * n, 2)),
            "heading_offset": rng.uniform(-0.5, 0.5, (1, h)),
            "speed": rng.uniform(0.8, 1.2, 1),
        }
        for _ in range(frames)
    ]
    heads = [{k: jnp.asarray(v, jnp.float32) for k, v in head.items()} for head in heads]
    head_speed = lambda t: 10.0 * float(heads[t]["speed"][0])
    start_yaw = 0.7  # 0.3 rad past its bin's centre: the curve rolls it into the next bin
    start_pose = jnp.asarray([[3.0, 4.0, math.cos(start_yaw), math.sin(start_yaw), 10.0]], jnp.float32)
    start_pose = start_pose if known_start else None
    odometry_start = start_pose if known_start else jnp.asarray([[0.0, 0.0, 1.0, 0.0, head_speed(0)]], jnp.float32)
    poses, _, covariances = jax.jit(ego_motion.follow, static_argnums=0)(
        model, odometry_start, jnp.asarray(commands[None, :, 0]), scans[None]
    )
    poses, heading_var_rad2 = np.asarray(poses[0], np.float64), np.asarray(covariances[0, :, 2, 2], np.float64)

    settings = dict(floor=floor, power=power, speed_gain=gain, relocation=relocation)
    settings.update(heading_noise_scale=heading_scale, full_measure_m=full_measure_m, stopped_share=standing)
    step = jax.jit(
        lambda state, head, action, first, scan: pose_belief.filter_step(
            state, head, action, first, grid, model, start_pose=start_pose, scan=scan, **settings
        )
    )
    state = pose_belief.init_state(1, grid)
    centres = -np.pi + (np.arange(h) + 0.5) * grid.bin_rad
    yaw_of = lambda pose: math.atan2(pose[3], pose[2])
    stats = {"rolls": set(), "position_diffused": False, "split_covers": False, "capped": False}
    heading_shares = []
    for t in range(frames):
        first = jnp.asarray([t == 0])
        state, _ = step(state, heads[t], jnp.asarray(commands[t]), first, scans[t][None])
        if t == 0:
            if known_start:
                belief, offset = (np.asarray(x[0], np.float64) for x in pose_belief.start_at(start_pose, grid))
                speed = 10.0
            else:
                belief, offset, speed = np.ones((h, n, n)), 0.0, head_speed(0)
            share = 1.0
        else:
            before, after = poses[t - 1], poses[t]
            turn = lambda a, v: np.stack([np.cos(a) * v[0] - np.sin(a) * v[1], np.sin(a) * v[0] + np.cos(a) * v[1]], -1)
            chord = turn(-yaw_of(before), after[:2] - before[:2])  # in the car's axes at the frame before
            ds, dyaw = float(np.linalg.norm(chord)), float(wrap(yaw_of(after) - yaw_of(before)))
            move = turn(centres + offset, chord)  # [h, 2]
            if known_start:
                heading_var = max(heading_var_rad2[t] - heading_var_rad2[t - 1], 0.0)
            else:
                heading_var = heading_scale * model.heading_noise_rad2pm * ds
            heading_shares.append(0.5 * heading_var / grid.bin_rad**2)
            matrix = np_transition(move, ds, offset + dyaw, model, n, grid.cell_m, h, relocation, heading_var, stats)
            belief = (matrix @ belief.ravel()).reshape(h, n, n)
            offset = offset + dyaw - np.round((offset + dyaw) / grid.bin_rad) * grid.bin_rad
            speed = after[4] + gain * (head_speed(t) - after[4])
            share = max(min(ds / full_measure_m, 1.0), standing)
        head = {k: np.asarray(v[0], np.float64) for k, v in heads[t].items()}
        belief = belief * np_measurement(head["place_logit"], head["heading_logit"], floor, n, h) ** (power * share)
        belief /= belief.sum()
        np.testing.assert_allclose(state.belief[0], belief, rtol=2e-4, atol=1e-8, err_msg=f"frame {t}")
        np.testing.assert_allclose(state.speed_mps[0], speed, rtol=1e-5, err_msg=f"frame {t}")
        np.testing.assert_allclose(state.yaw_offset_rad[0], offset, atol=1e-5, err_msg=f"frame {t}")
    # the test exercised what it claims: a roll, position noise, and a heading diffusion that moves mass
    assert stats["rolls"] - {0} and stats["position_diffused"], stats
    assert max(heading_shares) > 1e-3, heading_shares


# ----------------------------------------------------------------------------- credible regions


def test_region_share_against_levels():
    """Random beliefs (spiky and flat, plus a uniform one and a point), heading offsets and true poses (half
    drawn from the belief itself, half anywhere): ``region_share`` for the place and for (heading bin, place)
    equals :func:`np_region_share` of the place marginal and of the whole belief, the true cell and bin found
    here by hand, within float32's rounding of the sums (relative to the truth's own probability)."""
    grid = pose_belief.Grid(cell_m=20.0, heading_bins=12)
    n, h, b = grid.n, grid.heading_bins, 48
    rng = np.random.default_rng(5)
    belief = rng.gamma(rng.choice([0.05, 0.3, 3.0], (b, 1, 1, 1)), size=(b, h, n, n))
    belief[0] = 1.0  # uniform: every state holds the region's share of itself
    belief[1] = 0.0
    belief[1, 3, 7, 9] = 1.0  # a point
    belief = (belief / belief.sum(axis=(1, 2, 3), keepdims=True)).astype(np.float32)
    offset = rng.uniform(-0.5, 0.5, b) * grid.bin_rad
    # true states: from the belief for even rows and the point, uniform for the other odd rows; a point
    # inside the cell and bin
    flat = belief.reshape(b, -1).astype(np.float64)
    state_index = np.array(
        [
            rng.choice(h * n * n, p=f / f.sum()) if r % 2 == 0 or r == 1 else rng.integers(h * n * n)
            for r, f in enumerate(flat)
        ]
    )
    k, i, j = state_index // (n * n), state_index // n % n, state_index % n
    x = pose_belief.AREA_ORIGIN_M + (j + rng.uniform(0.05, 0.95, b)) * grid.cell_m
    y = pose_belief.AREA_ORIGIN_M + (i + rng.uniform(0.05, 0.95, b)) * grid.cell_m
    yaw = -np.pi + (k + rng.uniform(0.05, 0.95, b)) * grid.bin_rad + offset
    pose = np.stack([x, y, np.cos(yaw), np.sin(yaw), np.zeros(b)], -1).astype(np.float32)
    state = pose_belief.init_state(b, grid).replace(
        belief=jnp.asarray(belief), yaw_offset_rad=jnp.asarray(offset, jnp.float32)
    )
    # the true cell and bin from the pose, by hand
    column = lambda u: np.floor((u - pose_belief.AREA_ORIGIN_M) / grid.cell_m).astype(int)
    cell = column(y) * n + column(x)
    true_k = (np.floor((wrap(yaw - offset) + np.pi) / grid.bin_rad).astype(int)) % h
    place = belief.reshape(b, h, -1).astype(np.float64).sum(1)
    p_true = np.stack([place[np.arange(b), cell], flat[np.arange(b), true_k * n * n + cell]], -1)
    for mass in (0.5, 0.95):
        got = np.asarray(pose_belief.region_share(state, jnp.asarray(pose), grid, mass))
        want = np.stack(
            [
                [np_region_share(place[r], mass)[cell[r]] for r in range(b)],
                [np_region_share(flat[r], mass)[true_k[r] * n * n + cell[r]] for r in range(b)],
            ],
            -1,
        )
        np.testing.assert_array_less(np.abs(got - want), 1e-5 + 1e-5 / np.maximum(p_true, 1e-30))
        np.testing.assert_allclose(got[0], mass, rtol=1e-5)  # uniform
        np.testing.assert_allclose(got[1], mass, rtol=1e-5)  # the point's own state
        assert ((got == 0) & (want == 0)).any() and ((got == 1) & (want == 1)).any()  # wholly in, wholly out
        assert ((got > 0.01) & (got < 0.99)).any()  # and a share


def test_the_region_holds_exactly_its_mass():
    """For truths drawn from the belief itself, the region's expected coverage is its mass: summed over
    every (heading bin, cell) of a coarse grid, each weighted by its probability, ``region_share`` gives
    ``mass`` for the joint region and, over every cell under the place marginal, for the place region
    (a region of whole cells would give more). Spiky, flat and point beliefs."""
    grid = pose_belief.Grid(cell_m=40.0, heading_bins=8)
    n, h = grid.n, grid.heading_bins
    rng = np.random.default_rng(11)
    beliefs = rng.gamma(np.array([0.05, 0.5, 5.0])[:, None, None, None], size=(3, h, n, n))
    point = np.zeros((1, h, n, n))
    point[0, 2, 4, 5] = 1.0
    beliefs = np.concatenate([beliefs, point])
    beliefs = (beliefs / beliefs.sum(axis=(1, 2, 3), keepdims=True)).astype(np.float32)
    # a pose at the centre of every (heading bin, cell), bin-major like the belief
    k, i, j = (a.ravel() for a in np.meshgrid(np.arange(h), np.arange(n), np.arange(n), indexing="ij"))
    centre = lambda c: pose_belief.AREA_ORIGIN_M + (c + 0.5) * grid.cell_m
    yaw = -np.pi + (k + 0.5) * grid.bin_rad
    pose = jnp.asarray(np.stack([centre(j), centre(i), np.cos(yaw), np.sin(yaw), 0 * yaw], -1), jnp.float32)
    for belief in beliefs:
        state = pose_belief.init_state(len(k), grid).replace(belief=jnp.broadcast_to(belief, (len(k),) + belief.shape))
        p = np.asarray(belief, np.float64)
        for mass in (0.5, 0.95):
            share = np.asarray(pose_belief.region_share(state, pose, grid, mass), np.float64)
            joint = np.sum(p.ravel() * share[:, 1])
            place = np.sum(p.sum(0).ravel() * share[: n * n, 0])  # heading bin 0's poses: every cell once
            assert joint == pytest.approx(mass, abs=2e-5) and place == pytest.approx(mass, abs=2e-5)


# ----------------------------------------------------------------------------- motion: odometry and histogram


def known_start_track(model, start, commands, grid, restart_at=None):
    """The filter's known-start odometry (``measure=False``) driven by ``commands`` [T, 2] alone from
    ``start`` [5] (restarting there at frame ``restart_at``): poses [T+1, 5] and actuators [T+1, 2]."""
    step = jax.jit(lambda s, a, f, p: pose_belief.filter_step(s, None, a, f, grid, model, start_pose=p, measure=False))
    state = pose_belief.init_state(1, grid)
    poses, actuators = [], []
    for t in range(len(commands) + 1):
        action = commands[t - 1 : t] if t else np.full((1, 2), 0.7)  # (a first frame's command means nothing)
        first = jnp.asarray([t == 0 or t == restart_at])
        state, pose = step(state, jnp.asarray(action, jnp.float32), first, jnp.asarray(start[None], jnp.float32))
        poses.append(np.asarray(pose[0]))
        actuators.append(np.asarray(state.actuator[0]))
    return np.array(poses), np.array(actuators)


def smooth_commands(rng, frames):
    """Pedal and steering commands that vary smoothly, as a driver's do."""
    t = np.arange(frames) * DT_S
    pedal = 0.35 * np.sin(2 * np.pi * t / 7.0 + rng.uniform(0, 6)) + 0.05 + 0.05 * rng.normal(size=frames)
    steer = 0.15 * np.sin(2 * np.pi * t / 11.0 + rng.uniform(0, 6)) + 0.02 * rng.normal(size=frames)
    return np.stack([pedal, steer], -1)


@pytest.mark.slow
@pytest.mark.parametrize("spread", [False, True])
def test_known_start_odometry_follows_the_motion_model(spread):
    """The known-start odometry with a lagged, biased, understeering model, over 600 frames of varying pedal
    and steering, restarting at frame 350: its poses, speed and actuators follow the motion model integrated
    here in float64 (:func:`np_odometry`) from the start, and again from the restart, whether its belief is a
    point or spread as the odometry's fitted errors (the pose is the odometry's either way)."""
    grid = pose_belief.Grid(cell_m=10.0, heading_bins=36)
    rng = np.random.default_rng(7)
    commands = smooth_commands(rng, 600).astype(np.float32)
    start = np.array([150.0, 210.0, math.cos(2.0), math.sin(2.0), 7.0])
    restart = 350
    model = LAGGED
    if spread:
        model = dataclasses.replace(LAGGED, odometry_location_scale=2.0, odometry_heading_scale=3.0)
    got, got_actuator = known_start_track(model, start, commands, grid, restart_at=restart)
    # frame t's pose comes from commands 0..t-1; after the restart from commands restart..t-1
    first_part, first_act = np_odometry(LAGGED, start, commands[: restart - 1].astype(np.float64))
    second_part, second_act = np_odometry(LAGGED, start, commands[restart:].astype(np.float64))
    want = np.concatenate([first_part, second_part])
    want_actuator = np.concatenate([np.zeros((1, 2)), first_act, np.zeros((1, 2)), second_act])
    travelled = np.sum(np.linalg.norm(np.diff(first_part[:, :2], axis=0), axis=-1))
    assert travelled > 150.0 and np.ptp(first_part[:, 4]) > 3.0  # it drove and changed speed
    assert np.ptp(np.unwrap(np.arctan2(first_part[:, 3], first_part[:, 2]))) > 1.0  # and turned
    error_m = np.linalg.norm(got[:, :2] - want[:, :2], axis=-1)
    heading_error = np.abs(wrap(np.arctan2(got[:, 3], got[:, 2]) - np.arctan2(want[:, 3], want[:, 2])))
    assert error_m.max() < 0.05, error_m.max()  # float32 over a 480 m area
    assert heading_error.max() < 1e-3, heading_error.max()
    np.testing.assert_allclose(got[:, 4], want[:, 4], atol=1e-3)
    np.testing.assert_allclose(got_actuator, want_actuator, atol=1e-5)


def histogram_track(model, start, commands, grid):
    """The histogram's own motion (``predict`` moved by ``motion.step``) of a point mass at ``start`` [5]
    driven by ``commands`` [T, 2] (actuators starting at the first): the belief's mean poses [T+1, 5]."""
    belief, offset = pose_belief.start_at(jnp.asarray(start[None], jnp.float32), grid)
    state = pose_belief.init_state(1, grid).replace(
        belief=belief, yaw_offset_rad=offset, speed_mps=jnp.asarray(start[None, 4], jnp.float32)
    )
    predict = jax.jit(
        lambda b, m, o, d: pose_belief.predict(b, m, o, d, model.heading_noise_rad2pm * d, model, grid),
        compiler_options=OPTIMISED,
    )
    actuator = jnp.asarray(commands[:1], jnp.float32)
    poses = [pose_belief.mean_pose(state, grid)[0]]
    for command in commands:
        yaw = jnp.asarray(grid.bin_centres())[None] + state.yaw_offset_rad[:, None]
        actuator, speed, ds, move, dyaw = motion_lib.step(
            model, actuator, jnp.asarray(command[None], jnp.float32), state.speed_mps, yaw
        )
        belief, offset = predict(state.belief[0], move[0], state.yaw_offset_rad[0] + dyaw[0], ds[0])
        state = state.replace(belief=belief[None], yaw_offset_rad=offset[None], speed_mps=speed)
        poses.append(pose_belief.mean_pose(state, grid)[0])
    return np.array(poses)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["exact_straight", "exact_turning", "lagged_position_noise"])
def test_histogram_motion_keeps_a_point_mass_mean_on_the_motion_model(case):
    """A point mass (bilinear over cells, one bin and the heading offset) moved by the histogram step by
    step: its mean follows the motion model integrated in NumPy (:func:`np_odometry`), turning too (the
    bilinear split keeps the mean exact, the offset carries the heading; position noise diffuses the mass
    symmetrically, so it keeps the mean too; heading noise would not, and is off here)."""
    grid = pose_belief.Grid(cell_m=5.0, heading_bins=72)
    yaw0 = float(grid.bin_centres()[20])
    start = np.array([123.4, 211.7, math.cos(yaw0), math.sin(yaw0), 6.0])
    rng = np.random.default_rng(3)
    pedal = rng.uniform(-1.0, 1.0, 120)
    if case == "lagged_position_noise":
        model = dataclasses.replace(LAGGED, heading_noise_rad2pm=0.0, position_noise_m2pm=0.5)
        commands = np.stack([pedal, np.full(120, 0.12)], -1)
    else:
        model = MotionModel()
        commands = np.stack([pedal, np.full(120, 0.0 if case == "exact_straight" else 0.12)], -1)
    got = histogram_track(model, start, commands, grid)
    want, _ = np_odometry(model, start, commands)
    error_m = np.linalg.norm(got[:, :2] - want[:, :2], axis=-1)
    yaw = lambda p: np.arctan2(p[:, 3], p[:, 2])
    heading_error = np.abs(wrap(yaw(got) - yaw(want)))
    assert np.sum(np.linalg.norm(np.diff(want[:, :2], axis=0), axis=-1)) > 50.0  # it drove
    np.testing.assert_allclose(got[:, 4], want[:, 4], atol=1e-4)
    if case == "exact_straight":
        assert error_m.max() < 1e-3 and heading_error.max() < 1e-5
    else:
        assert abs(wrap(yaw(want)[-1] - yaw0)) > 1.0  # it turned by more than a radian
        assert error_m.max() < 0.01 and heading_error.max() < 1e-4, (error_m.max(), heading_error.max())


# ----------------------------------------------------------------------------- real drives


def ego_drives(key, town, world_cfg, warmup_steps, num_worlds, frames):
    """Drives of the ego (world.step, no sensors): NumPy (poses [W, T, 5] (x, y, cos, sin, speed), the
    commands applied from frame t-1 to frame t [W, T, 2] (frame 0's: the warm-up's last))."""

    @functools.partial(jax.jit, compiler_options=OPTIMISED)
    def run(keys):
        def one(k):
            state = rollout.advance(world.reset(k, town, world_cfg), town, warmup_steps)

            def body(s, _):
                box = s.veh_box[world.EGO]
                pose = jnp.stack([box[0], box[1], jnp.cos(box[2]), jnp.sin(box[2]), s.veh_speed_mps[world.EGO]])
                return world.step(s, town), (pose, s.ego_action)

            return jax.lax.scan(body, state, None, length=frames)[1]

        return jax.vmap(one)(keys)

    return jax.tree.map(np.asarray, run(jax.random.split(key, num_worlds)))


@pytest.mark.slow
def test_the_world_moves_its_ego_by_the_exact_motion_model(town):
    """A real drive of a world whose ego plant is exact (all its fields zero): the known-start odometry
    with ``MotionModel()`` fed the logged commands alone stays on the true path for 1,000 frames."""
    cfg = config.get_config("tiny")
    pose, prev_action = ego_drives(
        jax.random.PRNGKey(4), town, config.replace(cfg, world=EXACT_PLANT).world, cfg.data.warmup_steps, 1, 1000
    )
    got, _ = known_start_track(MotionModel(), pose[0, 0], prev_action[0, 1:], GRID)
    travelled = np.sum(np.linalg.norm(np.diff(pose[0, :, :2], axis=0), axis=-1))
    error_m = np.linalg.norm(got[:, :2] - pose[0, :, :2], axis=-1)
    assert travelled > 200.0
    assert error_m.max() < 0.05, (error_m.max(), travelled)  # float32 rounding


COVERAGE_DRIVES, COVERAGE_FRAMES = 4, 600


@pytest.fixture(scope="module")
def plant_drives(town):
    """Drives of the tiny config's world, its ego with the default plant (lag, steering offset, gain,
    understeer, noise), from keys the calibration does not use."""
    cfg = config.get_config("tiny")
    return ego_drives(jax.random.PRNGKey(29), town, cfg.world, cfg.data.warmup_steps, COVERAGE_DRIVES, COVERAGE_FRAMES)


def blind_filter(model, pose, prev_action, grid, heading_noise_scale):
    """The filter from the true first pose, measuring a head that knows nothing of place or heading (all
    logits equal) but the true speed, without relocation (its spread over all headings would cover any
    heading error by itself), its heading noise ``heading_noise_scale`` times the model's. NumPy:
    (``region_share`` of the true pose, [T, W, 2] (place; heading and place); the heading marginal
    [T, W, H]; the belief's mean heading after the last frame [W] rad)."""
    w, frames = pose.shape[:2]

    @functools.partial(jax.jit, compiler_options=OPTIMISED)
    def run(pose, prev_action):
        def body(state, xs):
            p, a, first = xs
            state, _ = pose_belief.filter_step(
                state,
                blank_head(w, grid, p[:, 4]),
                a,
                first,
                grid,
                model,
                start_pose=p,
                measure=True,
                relocation=0.0,
                heading_noise_scale=heading_noise_scale,
            )
            return state, (pose_belief.region_share(state, p, grid), jnp.sum(state.belief, axis=(-2, -1)))

        first = jnp.arange(frames) == 0
        xs = (jnp.swapaxes(pose, 0, 1), jnp.swapaxes(prev_action, 0, 1), jnp.broadcast_to(first[:, None], (frames, w)))
        last, (inside, heading) = jax.lax.scan(body, pose_belief.init_state(w, grid), xs)
        mean = pose_belief.mean_pose(last, grid)
        return inside, heading, jnp.arctan2(mean[:, 3], mean[:, 2])

    return jax.tree.map(np.asarray, run(jnp.asarray(pose), jnp.asarray(prev_action)))


def heading_variance_rad2(marginal, bin_rad):
    """Variance [...] of heading marginals [..., H] about their mean, unwrapped within half a turn of the mode."""
    h = marginal.shape[-1]
    rel = (np.arange(h) - np.argmax(marginal, -1)[..., None] + h // 2) % h - h // 2
    mean = np.sum(marginal * rel, -1) / np.sum(marginal, -1)
    return (np.sum(marginal * rel**2, -1) / np.sum(marginal, -1) - mean**2) * bin_rad**2


@pytest.mark.slow
def test_calibrated_process_noise_covers_the_true_pose_without_measurements(plant_drives):
    """Four 600-frame drives (a minute each) of the training town's world, its ego with a plant the motion
    model does not know (lag, per-drive steering offset and gain, understeer, noise); the belief started at
    the true pose and told nothing of place or heading (:func:`blind_filter`), its heading noise at the
    factor the filter runs with (``pose_belief.HEADING_NOISE_SCALE``). The truth is the world's ego pose.
    With the motion model calibrated on other drives, the belief is neither overconfident nor wider than
    the calibration says:

    - the true cell and the true (heading bin, cell) lie in the 95 % regions in at least 99 % of the frames
      of every drive; the same check fails with the calibrated model's process noise removed, and with the
      exact bicycle (``MotionModel()``, no noise): the noise is what covers the plant;
    - the heading marginal's variance over the first 100 frames is the closed form of the diffusion, the
      factor times the calibrated noise times the distance driven (within 5 %; later, mass pushed off the
      grid narrows it on the drive that starts by the grid's corner);
    - the calibrated noise is the size of the motion model's errors: the noiseless model's heading (one bin
      that the motion alone moves) at each drive's end, in units of the calibrated std over the distance
      driven, has an rms within 0.5-1.5 (0.80; of 4 drives, 90 % of draws of a calibrated noise fall within
      0.42-1.54), so a noise 4 times too wide (0.40) or too narrow (1.6) fails.

    The 95 % regions alone cannot show a belief too wide: at the grid's 10 m and 10 degrees they hold the
    truth in every frame of these drives at a heading factor of 1, 8 or 10,000."""
    pose, prev_action = plant_drives
    travelled = np.sum(np.linalg.norm(np.diff(pose[:, :, :2], axis=1), axis=-1), 1)
    assert (travelled > 200.0).all(), travelled
    grid = pose_belief.grid_of(config.get_config("tiny").model)
    model = calibration.calibrate(config.get_config("tiny"))
    assert model.heading_noise_rad2pm > 0 and model.position_noise_m2pm > 0
    scale = pose_belief.HEADING_NOISE_SCALE
    inside, marginal, _ = blind_filter(model, pose, prev_action, grid, scale)
    share = inside.mean(0)  # [W, 2]: share of frames inside
    assert (share >= 0.99).all(), share
    distance_m = np.concatenate(
        [np.zeros((len(pose), 1)), np.cumsum(np.linalg.norm(np.diff(pose[:, :, :2], axis=1), axis=-1), 1)], 1
    ).T  # [T, W], driven since the start
    np.testing.assert_allclose(
        heading_variance_rad2(marginal[:100], grid.bin_rad),
        scale * model.heading_noise_rad2pm * distance_m[:100],
        rtol=0.05,
        atol=1e-5,
    )
    noiseless = dataclasses.replace(model, heading_noise_rad2pm=0.0, position_noise_m2pm=0.0)
    for without_noise in (MotionModel(), noiseless):
        inside, _, mean_yaw = blind_filter(without_noise, pose, prev_action, grid, scale)
        share = inside.mean(0)
        assert (share[:, 1] < 0.99).any(), (without_noise, share)
    # mean_yaw: the noiseless model's, the loop's last
    heading_error = wrap(mean_yaw - np.arctan2(pose[:, -1, 3], pose[:, -1, 2]))
    z = heading_error / np.sqrt(model.heading_noise_rad2pm * distance_m[-1])
    assert 0.5 < np.sqrt(np.mean(z**2)) < 1.5, z


def test_negative_log_likelihood_of_a_uniform_belief_is_the_log_volume():
    state = pose_belief.init_state(3, GRID)
    nll = pose_belief.negative_log_likelihood(state, jnp.asarray(random_poses(3)), GRID)
    np.testing.assert_allclose(nll, math.log(480.0**2 * 2 * math.pi), rtol=1e-5)


@pytest.mark.slow
def test_position_estimate_is_the_local_mean_around_the_mode():
    """A belief holding a point bilinearly (four neighbouring cells) reads back that point; a second,
    smaller mode far away does not pull the estimate."""
    pose = jnp.asarray(random_poses(5, seed=5))
    belief, _ = pose_belief.start_at(pose, GRID)
    far = jnp.roll(belief, (GRID.n // 2, GRID.n // 2), axis=(2, 3))  # the same shape 240 m away
    head = head_naming(pose, GRID)
    for b in (belief, 0.7 * belief + 0.3 * far):
        got = pose_belief.estimate(b, head, pose[:, 4], GRID)
        np.testing.assert_allclose(got[:, :2], pose[:, :2], atol=1e-3)
        np.testing.assert_allclose(got[:, 2:], pose[:, 2:], atol=1e-4)  # heading from the head's offset


def test_a_spread_belief_is_the_gaussian_it_stands_for():
    """``spread_at``: its 95 % regions (place; place and heading) hold 94-96 % of poses drawn from the
    Gaussian it stands for (20,000 draws: the sampling's std is 0.15 point),
    its mean is the pose, and a std of 0 puts all the mass in the pose's own cell and bin."""
    grid = pose_belief.Grid(cell_m=5.0, heading_bins=36)
    pose = np.array([[203.0, 151.0, math.cos(0.7), math.sin(0.7), 5.0]], np.float32)
    std_m = np.array([9.0, 6.0])
    belief, offset = pose_belief.spread_at(jnp.asarray(pose), jnp.asarray(std_m[None]), jnp.asarray([0.2]), grid)
    belief = np.asarray(belief[0], np.float64)
    assert float(offset[0]) == 0.0 and abs(belief.sum() - 1.0) < 1e-5
    rng = np.random.default_rng(3)
    xy = pose[0, :2] + rng.normal(0, 1.0, (20000, 2)) * std_m
    yaw = 0.7 + rng.normal(0, 0.2, 20000)
    cell = np.asarray(pose_belief.true_cell(jnp.asarray(xy), grid)[0])
    k = np.asarray(pose_belief.true_bin(jnp.asarray(yaw), grid)[0])
    place, flat = belief.sum(0).ravel(), belief.reshape(-1)
    region = lambda p, index: np_region_share(p, 0.95)[index]

    assert 0.94 <= region(place, cell).mean() <= 0.96
    assert 0.94 <= region(flat, k * grid.num_cells + cell).mean() <= 0.96
    state = pose_belief.init_state(1, grid).replace(belief=jnp.asarray(belief[None], jnp.float32))
    mean = np.asarray(pose_belief.mean_pose(state, grid)[0])
    np.testing.assert_allclose(mean[:2], pose[0, :2], atol=0.05)
    assert abs(math.atan2(mean[3], mean[2]) - 0.7) < 0.005
    point, _ = pose_belief.spread_at(jnp.asarray(pose), jnp.zeros((1, 2)), jnp.zeros(1), grid)
    own = np.zeros(np.asarray(point).shape[1:])
    own[int(pose_belief.true_bin(jnp.asarray(0.7), grid)[0])].flat[
        int(pose_belief.true_cell(jnp.asarray(pose[0, :2]), grid)[0])
    ] = 1.0
    np.testing.assert_allclose(np.asarray(point[0]), own, atol=1e-6)


def test_the_spread_scale_recovers_a_planted_factor():
    """``calibration.spread_scale`` on errors drawn from Gaussians of covariance 3 x C (2-D, each draw its own
    C) and 0.5 x v (1-D) under C and v returns 3 and 0.5 within 5 %: the 95 % quantile of the squared
    Mahalanobis distances over chi-square's, as ``calibration.squared_errors`` computes them."""
    rng = np.random.default_rng(0)
    n = 40000
    root = rng.normal(size=(n, 2, 2))
    covariance = root @ np.swapaxes(root, 1, 2) + 0.1 * np.eye(2)
    error = np.einsum("nij,nj->ni", np.linalg.cholesky(3.0 * covariance), rng.normal(size=(n, 2)))
    assert abs(calibration.spread_scale(calibration.squared_errors(error, covariance), 2) / 3.0 - 1) < 0.05
    variance = rng.uniform(0.1, 2.0, n)
    heading = rng.normal(size=n) * np.sqrt(0.5 * variance)
    assert abs(calibration.spread_scale(heading**2 / variance, 1) / 0.5 - 1) < 0.05
