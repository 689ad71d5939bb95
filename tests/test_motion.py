"""Tests of the ego's bicycle step (``sim/motion.py``) and of the wheel odometry that integrates it
(``sim/odometry.py``).

Independent truths: the closed form of a drive at constant curvature (:func:`_circle_drive`); the world's ego
update re-implemented here in float64; the world's own ego path (world.reset / world.step).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from e2e_percep_jax.config import DEFAULT_TOWN_SEED, WorldConfig
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import motion, odometry, world
from e2e_percep_jax.sim import town as town_lib
from e2e_percep_jax.sim.motion import DT_S, WHEELBASE_M


def pose_of(x, y, yaw, speed=0.0):
    return np.array([x, y, np.cos(yaw), np.sin(yaw), speed])


# ---------------------------------------------------------------------------------- constant curvature


def _circle_drive(start_xy, start_yaw_rad, ds_m, dyaw_rad, num_steps):
    """Closed form of ``num_steps`` equal steps: the rear axle drives ``ds_m`` along the mid-step heading
    while the heading turns by ``dyaw_rad``, the centre half a wheelbase ahead of the rear axle.

    Each step is a chord of length ds turned dyaw / 2 from the heading, so the rear axle visits the corners
    of a regular polygon inscribed in the circle of radius ``R = ds / (2 sin(dyaw / 2))`` (signed: < 0 turning
    right) about ``O = rear_0 + R (-sin yaw_0, cos yaw_0)``; the centre then circles O at radius
    ``hypot(R, wheelbase / 2)``. (R is not 1 / curvature = ds / dyaw: the step's chord is ds, the arc's would
    be shorter; they differ by a relative dyaw^2 / 24.)

    Returns (centres [N+1, 2], yaws [N+1] rad, O [2], the centre's radius m).
    """
    half_m = 0.5 * WHEELBASE_M
    radius_m = ds_m / (2.0 * np.sin(0.5 * dyaw_rad))
    rear0_xy = start_xy - half_m * np.array([np.cos(start_yaw_rad), np.sin(start_yaw_rad)])
    rotation_xy = rear0_xy + radius_m * np.array([-np.sin(start_yaw_rad), np.cos(start_yaw_rad)])
    yaw_rad = start_yaw_rad + dyaw_rad * np.arange(num_steps + 1)
    rear_xy = rotation_xy + radius_m * np.stack([np.sin(yaw_rad), -np.cos(yaw_rad)], 1)
    centres_xy = rear_xy + half_m * np.stack([np.cos(yaw_rad), np.sin(yaw_rad)], 1)
    return centres_xy, yaw_rad, rotation_xy, np.hypot(radius_m, half_m)


def _assert_on_circle(centres_xy, yaw_rad, start_xy, start_yaw_rad, ds_m, dyaw_rad, atol_m):
    """Centres [N+1, 2] and yaws [N+1] (wrapped or not) of a drive against :func:`_circle_drive`'s closed form."""
    num_steps = len(centres_xy) - 1
    want_xy, want_yaw, rotation_xy, radius_m = _circle_drive(start_xy, start_yaw_rad, ds_m, dyaw_rad, num_steps)
    np.testing.assert_allclose(np.linalg.norm(centres_xy - rotation_xy, axis=1), radius_m, atol=atol_m)
    np.testing.assert_allclose(centres_xy, want_xy, atol=atol_m)
    np.testing.assert_allclose(geo.wrap_angle(yaw_rad - want_yaw), 0.0, atol=atol_m / radius_m)


# Start far from the origin (town coordinates), turning left and right, past a full turn (20 m radius, 150 steps).
START_XY, SPEED_MPS, NUM_STEPS = np.array([120.0, -40.0]), 10.0, 150
# float32 (JAX): positions of ~150 m (ulp 1.5e-5 m) summed over 150 steps drift ~5e-4 m. Tight enough to tell
# the step's circle from the arc of radius 1 / curvature (up to 4 mm off here).
FLOAT32_ATOL_M = 1e-3


@pytest.mark.parametrize("xp", [np, jnp], ids=["numpy", "jax"])
def test_centre_move_drives_constant_curvature_on_the_closed_form_circle(xp):
    """Three headings at once (K = 3), each driven at one yaw rate left then right; NumPy float64 stays
    NumPy float64 (what odometry relies on), JAX float32 stays JAX."""
    start_yaws_rad = np.array([2.5, -0.3, 3.1])
    ds_m = SPEED_MPS * DT_S
    for yaw_rate_rps in (0.5, -0.5):
        dyaw_rad = yaw_rate_rps * DT_S
        centre_xy, yaw_rad = xp.asarray(np.tile(START_XY, (3, 1))), xp.asarray(start_yaws_rad)
        centres, yaws = [centre_xy], [yaw_rad]
        for _ in range(NUM_STEPS):
            move = motion.centre_move(xp.asarray(ds_m), xp.asarray(dyaw_rad), yaw_rad)  # [K, 2]
            assert isinstance(move, jax.Array) == (xp is jnp)
            assert move.dtype == (np.float64 if xp is np else jnp.float32)
            centre_xy, yaw_rad = centre_xy + move, yaw_rad + dyaw_rad
            centres.append(centre_xy)
            yaws.append(yaw_rad)
        centres, yaws = np.asarray(xp.stack(centres, 1), np.float64), np.asarray(xp.stack(yaws, 1), np.float64)
        for k, start_yaw_rad in enumerate(start_yaws_rad):
            atol_m = 1e-9 if xp is np else FLOAT32_ATOL_M
            _assert_on_circle(centres[k], yaws[k], START_XY, start_yaw_rad, ds_m, dyaw_rad, atol_m)


@pytest.mark.parametrize("xp", [np, jnp], ids=["numpy", "jax"])
def test_exact_motion_model_at_constant_steering_drives_the_closed_form_circle(xp):
    """``advance_pose`` through the exact bicycle (the default model): no pedal keeps the speed, a constant
    steering angle gives the curvature tan(steer) / wheelbase. It computes in JAX whatever the input."""
    model = motion.MotionModel()
    steer_rad = np.array([0.14, -0.14])  # left and right, radius ~19 m
    start_yaws_rad = np.array([2.5, -0.3])
    command = xp.asarray(np.stack([np.zeros(2), steer_rad], 1))  # [B, 2] (pedal, steering)
    pose = xp.asarray(np.stack([pose_of(*START_XY, yaw, SPEED_MPS) for yaw in start_yaws_rad]))
    actuator, poses = command, [pose]
    for _ in range(NUM_STEPS):
        actuator, pose = motion.advance_pose(model, actuator, command, pose)
        poses.append(pose)
    poses = np.asarray(jnp.stack(poses, 1), np.float64)  # [B, N+1, 5]
    np.testing.assert_allclose(poses[..., 4], SPEED_MPS, rtol=1e-6)
    ds_m = SPEED_MPS * DT_S
    for b in range(2):
        dyaw_rad = ds_m * np.tan(steer_rad[b]) / WHEELBASE_M
        yaw_rad = geo.pose_yaw(poses[b])
        _assert_on_circle(poses[b, :, :2], yaw_rad, START_XY, start_yaws_rad[b], ds_m, dyaw_rad, FLOAT32_ATOL_M)


def test_odometry_at_constant_speed_and_yaw_rate_drives_the_closed_form_circle():
    start_yaw_rad, ds_m = 2.5, SPEED_MPS * DT_S
    start_pose = pose_of(*START_XY, start_yaw_rad, SPEED_MPS)
    for yaw_rate_rps in (0.5, -0.5):
        speed_mps, yaw_rate = np.full(NUM_STEPS, SPEED_MPS), np.full(NUM_STEPS, yaw_rate_rps)
        poses = odometry.dead_reckon(start_pose, speed_mps, yaw_rate)
        reckoner = odometry.DeadReckoner(start_pose)
        streamed = np.stack([reckoner.pose] + [reckoner.step(v, w) for v, w in zip(speed_mps, yaw_rate)])
        for drive in (poses, streamed):
            assert drive.dtype == np.float64
            _assert_on_circle(
                drive[:, :2], geo.pose_yaw(drive), START_XY, start_yaw_rad, ds_m, yaw_rate_rps * DT_S, 1e-9
            )


# ------------------------------------------------------------------------------------ wheel odometry


def _bicycle_path_float64(num_steps, rng):
    """The world's ego update (world._drive_ego) re-implemented here in float64 under random controls."""
    half = 0.5 * world.WHEELBASE_M
    x, y, psi, v = 10.0, -5.0, 2.9, 6.0
    poses = [pose_of(x, y, psi, v)]
    for _ in range(num_steps):
        steer = rng.uniform(-0.3, 0.3)
        v_new = max(v + rng.uniform(-3, 3) * DT_S, 0.0)
        ds = 0.5 * (v + v_new) * DT_S
        psi_new = psi + ds * np.tan(steer) / world.WHEELBASE_M
        mid = 0.5 * (psi + psi_new)
        rx, ry = x - half * np.cos(psi) + ds * np.cos(mid), y - half * np.sin(psi) + ds * np.sin(mid)
        x, y, psi, v = rx + half * np.cos(psi_new), ry + half * np.sin(psi_new), geo.wrap_angle(psi_new), v_new
        poses.append(pose_of(x, y, psi, v))
    return np.stack(poses)


def test_dead_reckoning_exact_on_float64_bicycle():
    poses = _bicycle_path_float64(300, np.random.default_rng(0))
    est = odometry.dead_reckon(poses[0], *odometry.odometry_from_poses(poses))
    np.testing.assert_allclose(est, poses, atol=1e-9)
    reckoner = odometry.DeadReckoner(poses[0])
    speed, yaw_rate = odometry.odometry_from_poses(poses)
    streamed = np.stack([poses[0]] + [reckoner.step(v, w) for v, w in zip(speed, yaw_rate)])
    np.testing.assert_allclose(streamed, est, atol=1e-9)


@pytest.fixture(scope="module")
def world_ego_path():
    """Ego poses [201, 5] of a real world driven 200 steps (float32, as the world runs)."""
    town = town_lib.build_town(DEFAULT_TOWN_SEED)
    cfg = WorldConfig(num_vehicles=10)

    @jax.jit
    def roll(key):
        state = world.reset(key, town, cfg)

        def body(s, _):
            s = world.step(s, town)
            return s, (s.veh_box[world.EGO], s.veh_speed_mps[world.EGO])

        _, (boxes, speeds) = jax.lax.scan(body, state, None, length=200)
        boxes = jnp.concatenate([state.veh_box[world.EGO][None], boxes])
        return boxes, jnp.concatenate([state.veh_speed_mps[world.EGO][None], speeds])

    boxes, speeds = (np.asarray(a, np.float64) for a in roll(jax.random.PRNGKey(3)))
    poses = np.column_stack([boxes[:, :2], np.cos(boxes[:, 2]), np.sin(boxes[:, 2]), speeds])
    assert np.sum(np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1)) > 50.0  # it really drove
    return poses


@pytest.mark.slow
def test_dead_reckoning_reproduces_world_path(world_ego_path):
    poses = world_ego_path
    est = odometry.dead_reckon(poses[0], *odometry.odometry_from_poses(poses))
    # The world integrates in float32 (positions of a few hundred metres: ulp ~3e-5 m); the residual is its
    # rounding, accumulated over 200 steps.
    assert np.abs(est[:, :2] - poses[:, :2]).max() < 2e-3
    assert np.abs(geo.wrap_angle(geo.pose_yaw(est) - geo.pose_yaw(poses))).max() < 1e-5
    np.testing.assert_array_equal(est[:, 4], poses[:, 4])


@pytest.mark.slow
def test_dead_reckoning_error_grows_with_noise(world_ego_path):
    poses = world_ego_path
    rng = np.random.default_rng(7)
    errors = np.stack(
        [
            np.linalg.norm(
                odometry.dead_reckon(poses[0], *odometry.noisy_odometry(poses, 0.2, 0.02, rng))[:, :2] - poses[:, :2],
                axis=1,
            )
            for _ in range(64)
        ]
    )  # [runs, 201]
    mean_err = errors.mean(0)
    assert mean_err[0] == 0.0
    assert 0.0 < mean_err[20] < mean_err[100] < mean_err[200]
    # Same seed, same noise: reproducible.
    a = odometry.noisy_odometry(poses, 0.2, 0.02, np.random.default_rng(1))
    b = odometry.noisy_odometry(poses, 0.2, 0.02, np.random.default_rng(1))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
