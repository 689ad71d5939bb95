"""The pose belief (e2e_percep_jax/pose_belief.py): soft targets, mode + offset decoding, the histogram
filter's measurement update against a brute-force Bayes product, its motion step against the bicycle model,
and the world's ego moved by exactly that model."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from e2e_percep_jax import batch as batch_lib
from e2e_percep_jax import config, pose_belief, rollout, world
from e2e_percep_jax import town as town_lib

GRID = pose_belief.Grid(cell_m=10.0, heading_bins=36)


def random_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    yaw = rng.uniform(-np.pi, np.pi, n)
    return np.stack([rng.uniform(0, 420, n), rng.uniform(0, 420, n), np.cos(yaw), np.sin(yaw),
                     rng.uniform(0, 12, n)], -1).astype(np.float32)


def head_naming(pose, grid):
    """A belief head that names ``pose`` exactly: log soft targets, and the true offsets in every cell / bin."""
    cell, offset = pose_belief.true_cell(pose[:, :2], grid)
    k, heading_offset = pose_belief.true_bin(jnp.arctan2(pose[:, 3], pose[:, 2]), grid)
    return {"place_logit": jnp.log(pose_belief.place_target(pose[:, :2], grid)),
            "place_offset": jnp.broadcast_to(offset[:, None, :], (len(pose), grid.num_cells, 2)),
            "heading_logit": jnp.log(pose_belief.heading_target(jnp.arctan2(pose[:, 3], pose[:, 2]), grid)),
            "heading_offset": jnp.broadcast_to(heading_offset[:, None], (len(pose), grid.heading_bins)),
            "speed": pose[:, 4] / pose_belief.SPEED_SCALE_MPS}


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


def test_mode_and_offset_decoding_round_trips_a_pose():
    pose = random_poses(200, seed=1)
    got = np.asarray(pose_belief.decode(head_naming(jnp.asarray(pose), GRID), GRID))
    np.testing.assert_allclose(got, pose, atol=1e-4)  # float32 metres of a 480 m area


@pytest.mark.slow
def test_measurement_update_is_bayes_rule_against_brute_force():
    """A tiny grid (40 m cells: 12 x 12, 4 headings), a random prior and random head outputs, no motion:
    the filter's posterior equals (prior with the relocation share of each cell spread over its headings) x
    floored, tempered likelihood, normalised, cell by cell."""
    grid = pose_belief.Grid(cell_m=40.0, heading_bins=4)
    rng = np.random.default_rng(2)
    b, h, n = 2, grid.heading_bins, grid.n
    prior = rng.uniform(0.0, 1.0, (b, h, n, n))
    prior /= prior.sum(axis=(1, 2, 3), keepdims=True)
    head = {"place_logit": rng.normal(0, 2, (b, n * n)), "heading_logit": rng.normal(0, 2, (b, h)),
            "place_offset": np.zeros((b, n * n, 2)), "heading_offset": np.zeros((b, h)), "speed": np.zeros(b)}
    state = {"belief": jnp.asarray(prior, jnp.float32), "speed_mps": jnp.zeros(b), "yaw_offset_rad": jnp.zeros(b)}
    f32 = {k: jnp.asarray(v, jnp.float32) for k, v in head.items()}
    floor, power, relocation = 0.1, 0.7, 0.01
    new, _ = pose_belief.filter_step(state, f32, jnp.zeros((b, 2)), jnp.zeros(b, bool), grid, floor=floor, power=power,
                                     relocation=relocation)
    softmax = lambda x: np.exp(x - x.max()) / np.exp(x - x.max()).sum()
    for row in range(b):
        place = (1 - floor) * softmax(head["place_logit"][row]) + floor / (n * n)
        heading = (1 - floor) * softmax(head["heading_logit"][row]) + floor / h
        want = np.zeros((h, n, n))
        for k in range(h):
            for i in range(n):
                for j in range(n):
                    mixed = (1 - relocation) * prior[row, k, i, j] + relocation * prior[row, :, i, j].mean()
                    want[k, i, j] = mixed * (place[i * n + j] * heading[k]) ** power
        np.testing.assert_allclose(new["belief"][row], want / want.sum(), rtol=1e-4, atol=1e-9)


def bicycle(pose, speed, actions):
    """The world's kinematics by hand: rear axle half a wheelbase behind the centre, moved along the mid-step
    heading by the mean speed's arc; yaw rate from the steering. pose (x, y, yaw); returns [T+1, 3]."""
    x, y, yaw = pose
    half = world.WHEELBASE_M / 2
    out = [(x, y, yaw)]
    for accel, steer in actions:
        v_new = max(speed + accel * world.DT_S, 0.0)
        ds = 0.5 * (speed + v_new) * world.DT_S
        yaw_new = yaw + ds * math.tan(steer) / world.WHEELBASE_M
        rear = np.array([x, y]) - half * np.array([math.cos(yaw), math.sin(yaw)])
        mid = 0.5 * (yaw + yaw_new)
        rear = rear + ds * np.array([math.cos(mid), math.sin(mid)])
        x, y = rear + half * np.array([math.cos(yaw_new), math.sin(yaw_new)])
        yaw, speed = yaw_new, v_new
        out.append((x, y, yaw))
    return np.array(out)


def known_start_track(start, actions, grid):
    """The filter from a known start driven by ``actions`` [T, 2] alone: its poses [T+1, 5]."""
    state = pose_belief.init_state(1, grid)
    no_head = None
    poses = []
    for t in range(len(actions) + 1):
        action = jnp.asarray(actions[t - 1:t] if t else np.zeros((1, 2)), jnp.float32)
        state, pose = pose_belief.filter_step(state, no_head, action, jnp.asarray([t == 0]), grid,
                                              start_pose=jnp.asarray(start[None], jnp.float32))
        poses.append(np.asarray(pose[0]))
    return np.array(poses)


def histogram_track(start, actions, grid):
    """The histogram's own motion (``motion`` + ``predict``) of a point mass at ``start`` [5] driven by
    ``actions`` [T, 2]: the belief's mean poses [T+1, 5]."""
    belief, offset = pose_belief.start_at(jnp.asarray(start[None], jnp.float32), grid)
    state = {"belief": belief, "yaw_offset_rad": offset, "speed_mps": jnp.asarray(start[None, 4], jnp.float32)}
    poses = [pose_belief.mean_pose(state, grid)[0]]
    for action in actions:
        speed, move, dyaw = pose_belief.motion(jnp.asarray(action[None], jnp.float32), state["speed_mps"],
                                               state["yaw_offset_rad"], grid)
        belief, offset = pose_belief.predict(state["belief"][0], move[0], state["yaw_offset_rad"][0] + dyaw[0], grid)
        state = {"belief": belief[None], "yaw_offset_rad": offset[None], "speed_mps": speed}
        poses.append(pose_belief.mean_pose(state, grid)[0])
    return np.array(poses)


@pytest.mark.slow
@pytest.mark.parametrize("steer", [0.0, 0.12])
def test_histogram_motion_follows_the_bicycle_model_for_a_point_mass(steer):
    """A point mass (bilinear over cells, one bin and the heading offset) moved by the histogram step by
    step: its mean follows the bicycle model, turning too (the bilinear split keeps the mean exact and the
    heading never diffuses)."""
    grid = pose_belief.Grid(cell_m=5.0, heading_bins=72)
    yaw0 = float(grid.bin_centres()[20])
    start = np.array([123.4, 211.7, math.cos(yaw0), math.sin(yaw0), 6.0])
    rng = np.random.default_rng(3)
    actions = np.stack([rng.uniform(-1.0, 1.0, 120), np.full(120, steer)], -1)
    got = histogram_track(start, actions, grid)
    want = bicycle((start[0], start[1], yaw0), start[4], actions)
    error_m = np.linalg.norm(got[:, :2] - want[:, :2], axis=-1)
    heading_error = np.abs((np.arctan2(got[:, 3], got[:, 2]) - want[:, 2] + np.pi) % (2 * np.pi) - np.pi)
    assert np.sum(np.linalg.norm(np.diff(want[:, :2], axis=0), axis=-1)) > 50.0  # it drove
    if steer == 0.0:
        assert error_m.max() < 1e-3 and heading_error.max() < 1e-5
    else:
        assert abs(want[-1, 2] - yaw0) > 1.0  # it turned by more than a radian
        assert error_m.max() < 0.01 and heading_error.max() < 1e-4


@pytest.mark.slow
def test_the_world_moves_its_ego_by_the_filters_motion_model():
    """A real drive of the world: the filter started at the first true pose and fed the recorded actions
    alone (the known-start protocol, an odometry) stays on the true path for 1,000 frames."""
    cfg = config.get_config("tiny")
    town = town_lib.build_town(0)
    state = batch_lib.warm_up(jax.random.PRNGKey(4), town, cfg)
    one = jax.tree.map(lambda x: x[0], state)
    _, frames = jax.jit(lambda s: rollout.drive(s, town, 1000, cfg.data.image_size))(one)
    pose, action = np.asarray(frames["pose"]), np.asarray(frames["action"])
    got = known_start_track(pose[0], action[:-1], pose_belief.Grid(cell_m=10.0, heading_bins=36))
    travelled = np.sum(np.linalg.norm(np.diff(pose[:, :2], axis=0), axis=-1))
    error_m = np.linalg.norm(got[:, :2] - pose[:, :2], axis=-1)
    assert travelled > 200.0
    assert error_m.max() < 0.05, (error_m.max(), travelled)  # float32 rounding


def test_negative_log_likelihood_of_a_uniform_belief_is_the_log_volume():
    state = pose_belief.init_state(3, GRID)
    nll = pose_belief.negative_log_likelihood(state, jnp.asarray(random_poses(3)), GRID)
    np.testing.assert_allclose(nll, math.log(480.0 ** 2 * 2 * math.pi), rtol=1e-5)


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
