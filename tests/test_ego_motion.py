"""The lidar odometry (e2e_percep_jax/ego_motion.py): the scan matcher against known motions and the world's
true motion on a town the model never saw, its Kalman update against brute-force Bayes, the forward motion's
precision against its closed form and the walls that pin it, and the drive's steering offset and distance
scale learnt from scans of a drive with planted ones."""

import dataclasses
import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import OPTIMISED, buildings, lidar_scan, odometry_model, street

from e2e_percep_jax import calibration, ego_motion, pose_belief
from e2e_percep_jax import config as config_lib
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import motion, sensors


def _town_block(seed):
    rng = np.random.default_rng(seed)
    box = buildings(rng.uniform(-40, 40, (30, 2)), rng)
    return box[np.linalg.norm(box[:, :2], axis=-1) > 7]  # none over the ego


def test_the_scan_holds_the_lidars_walls_and_not_its_ground():
    """A world whose one building lies beyond the lidar's range has no return in its scan (the ground's are
    below the band); a wall 10 m ahead, 40 m wide, is at 10 / cos(azimuth) m in every azimuth that meets
    it, exactly."""
    assert ego_motion.SCAN_AZIMUTHS == sensors.LIDAR_NUM_AZIMUTHS
    far = np.array([[sensors.LIDAR_RANGE_M + 5.0, 0.0, 0.0, 4.0, 4.0]], np.float32)
    assert not np.any(np.asarray(lidar_scan(far, (0.0, 0.0, 0.0))))
    wall = np.array([[10.5, 0.0, 0.0, 1.0, 40.0]], np.float32)  # its near face at x = 10 m
    scan = np.asarray(lidar_scan(wall, (0.0, 0.0, 0.0)))
    azimuth = np.deg2rad(np.arange(360.0))
    meets = (np.cos(azimuth) > 0) & (np.abs(10.0 * np.tan(azimuth)) < 19.9)  # (off its ends by a margin)
    np.testing.assert_allclose(scan[meets], 10.0 / np.cos(azimuth[meets]), rtol=1e-5)
    assert not np.any(scan[np.cos(azimuth) < 0])  # nothing behind


def test_the_scan_sees_the_wall_over_a_van_and_not_the_van():
    """The scan keeps returns above the traffic: a van (2.6 m, the tallest vehicle) 8 m ahead of a wall 20 m
    ahead leaves the wall's range in the azimuths it covers, the beams that clear its roof seeing the wall;
    a kiosk (3 m, the lowest landmark) alone 10 m ahead is seen."""
    far = np.array([[300.0, 300.0, 0.0, 4.0, 4.0]], np.float32)  # (the scan casts a power of two of obstacles)
    wall = np.array([[20.5, 0.0, 0.0, 1.0, 40.0]], np.float32)  # its near face at x = 20 m
    van = np.array([[8.0, 0.0, 0.0, 2.0, 2.0]], np.float32)
    scan = np.asarray(lidar_scan(np.concatenate([wall, van]), (0.0, 0.0, 0.0), [6.0, 2.6]))
    np.testing.assert_allclose(scan[[0, 1, 359]], 20.0 / np.cos(np.deg2rad([0.0, 1.0, 1.0])), rtol=1e-5)
    kiosk = np.array([[10.5, 0.0, 0.0, 1.0, 3.0]], np.float32)
    scan = np.asarray(lidar_scan(np.concatenate([kiosk, far]), (0.0, 0.0, 0.0), [3.0, 3.0]))
    np.testing.assert_allclose(scan[0], 10.0, rtol=1e-5)


@pytest.mark.parametrize("motion_true", [(1.0, 0.2, 0.03), (0.6, -0.1, -0.05), (1.5, 0.0, 0.0)])
def test_a_known_motion_between_two_scans_is_recovered_exactly(motion_true):
    """Two scans of the same buildings from poses a known motion apart: the match from a prior off by more
    than the motion model errs over a keyframe interval (0.15 m, 0.1 m, 0.02 rad) recovers the motion to
    5 mm and 0.2 mrad (4 mm at 20 m: the line through two returns cuts a building's corners; the prior's
    weak pull included)."""
    box = _town_block(1)
    before, after = lidar_scan(box, (0.0, 0.0, 0.0)), lidar_scan(box, motion_true)
    found, num_returns, _ = ego_motion.match(before, after, jnp.asarray(motion_true) + jnp.asarray([0.15, -0.1, 0.02]))
    np.testing.assert_allclose(np.asarray(found)[:2], motion_true[:2], atol=0.005)
    assert abs(float(found[2]) - motion_true[2]) < 2e-4
    assert num_returns == min(np.sum(np.asarray(before) > 0), np.sum(np.asarray(after) > 0))


def test_the_kalman_update_is_bayes_rule_against_brute_force():
    """(e, bias, gain error) on a grid under the Gaussian prior, times the measurement's likelihood: the
    posterior means and the correction's covariance equal the update's."""
    c0, cov = np.array([3e-4, 0.01]), np.array([[2e-6, 1e-5], [1e-5, 4e-4]])
    h, white, scan, innovation = np.array([4.0, 0.05]), 2e-6, 3e-5, 0.008
    update = ego_motion.kalman_update(
        *(jnp.asarray(x, jnp.float32)[None] for x in (c0, cov, h, white, scan, innovation))
    )
    correction, covariance, turn, _ = (np.asarray(x, np.float64)[0] for x in update)
    # e = h . (c - c0) + w: the heading error the correction's error and the model's own errors make
    axes = [np.linspace(-6, 6, 61) * s for s in (np.sqrt(white), *np.sqrt(np.diag(cov)))]
    w, db, dk = np.meshgrid(*axes, indexing="ij")
    dc = np.stack([db, dk], -1)
    prior = np.exp(-0.5 * np.einsum("...i,ij,...j->...", dc, np.linalg.inv(cov), dc) - 0.5 * w**2 / white)
    e = dc @ h + w
    posterior = prior * np.exp(-0.5 * (innovation - e) ** 2 / scan)
    posterior /= posterior.sum()
    mean = lambda x: np.sum(posterior * x)
    assert abs(correction[0] - c0[0] - mean(db)) < 2e-6 and abs(correction[1] - c0[1] - mean(dk)) < 2e-4
    np.testing.assert_allclose(turn, mean(e), rtol=0.02)
    second = np.array([[mean(db * db), mean(db * dk)], [mean(dk * db), mean(dk * dk)]]) - np.outer(
        [mean(db), mean(dk)], [mean(db), mean(dk)]
    )
    np.testing.assert_allclose(covariance, second, rtol=0.03, atol=1e-9)


def _follow(model, speed_mps, command, scans):
    """``ego_motion.follow`` of one drive from the origin at ``speed_mps``, heading along x: commands [T, 2]
    applied frame to frame, scans [T + 1, SCAN_AZIMUTHS]. (poses, estimates, covariances) of its T + 1 frames."""
    start = jnp.asarray([[0.0, 0.0, 1.0, 0.0, speed_mps]], jnp.float32)
    previous = jnp.asarray(np.concatenate([command[:1], command]))[None]  # frame t's: the commands t-1 -> t
    return jax.tree.map(
        lambda x: x[0], jax.jit(ego_motion.follow, static_argnums=0)(model, start, previous, scans[None])
    )


def test_a_planted_steering_offset_and_distance_scale_are_learnt_from_the_scans_of_a_street():
    """A car whose path curves by a planted 0.004 / m more than its motion model says (a 0.6 degree
    steering offset), and which speeds up and slows down 3 % more than the model says (its distance scale),
    drives 600 frames down a street of buildings that follow its true path; the odometry learns both within
    10 %, and loses under a tenth of the heading and of the position that dead reckoning loses."""
    bias_1pm, accel_gain, frames = 0.004, 1.03, 600
    model = odometry_model()
    command = np.zeros((frames, 2), np.float32)
    command[:, 0] = 0.3 * np.sin(np.arange(frames) / 30.0)  # speeding up and slowing down between 6 and 11 m/s
    command[:, 1] = 0.03 * np.sin(np.arange(frames) / 40.0)  # a winding road
    speed = [6.0]
    for pedal in command[:, 0]:
        speed.append(float(motion.speed_step(speed[-1], accel_gain * motion.EGO_ACCEL_LIMIT_MPS2 * pedal)[0]))
    speed = np.asarray(speed)
    ds = 0.5 * (speed[1:] + speed[:-1]) * motion.DT_S
    model_dyaw = ds * np.asarray(motion.curvature(model, jnp.asarray(command[:, 1]), 0.5 * (speed[1:] + speed[:-1])))
    dyaw = model_dyaw + bias_1pm * ds
    xy, yaw, scans = street(ds, dyaw)
    run = lambda m: _follow(m, speed[0], command, scans)
    poses, estimates, _ = run(model)
    reckoned, _, _ = run(dataclasses.replace(model, scan_heading_noise_rad=0.0))
    assert abs(float(estimates[-1, 0]) - bias_1pm) < 0.1 * bias_1pm
    assert abs(float(estimates[-1, 2]) - (accel_gain - 1.0)) < 0.1 * (accel_gain - 1.0)
    heading_error = lambda p: abs(float(geo.wrap_angle(geo.pose_yaw(p[-1]) - yaw[-1])))
    assert heading_error(reckoned) > 0.9 * bias_1pm * ds.sum()  # dead reckoning misses all of it
    assert heading_error(poses) < 0.1 * heading_error(reckoned)
    position_error = lambda p: float(np.linalg.norm(np.asarray(p[-1, :2]) - xy[-1]))
    assert position_error(poses) < 0.1 * position_error(reckoned)


def test_a_turn_in_at_the_drives_start_is_not_taken_for_a_steering_offset():
    """A car with no steering offset starts a drive turning in: its path turns 0.03 rad over the first five
    frames, which its commands (straight ahead) do not show, as when its actuators were still turned from
    before the drive; then it drives straight for 145 frames. The first match puts the heading right, and the
    drive's curvature bias is never taken from it: the estimate stays within a tenth of the prior's spread of
    0 throughout, the heading ends within 1 mrad, and the position within 15 cm (what the first interval
    strayed across its path, which no match takes)."""
    frames = 150
    model = odometry_model()
    command = np.zeros((frames, 2), np.float32)
    ds = np.full(frames, 0.6)  # 6 m/s, the pedal at 0
    dyaw = np.where(np.arange(frames) < 5, 0.006, 0.0)
    xy, yaw, scans = street(ds, dyaw)
    poses, estimates, _ = _follow(model, 6.0, command, scans)
    assert float(np.max(np.abs(estimates[:, 0]))) < 0.1 * model.yaw_bias_std_1pm
    assert abs(float(geo.wrap_angle(geo.pose_yaw(poses[-1]) - yaw[-1]))) < 1e-3
    assert float(np.linalg.norm(np.asarray(poses[-1, :2]) - xy[-1])) < 0.15


def test_the_measured_belief_moves_by_the_lidar_odometry_given_the_scans():
    """On the training town (``measure``), a belief started at a known pose, under a head that says nothing
    (flat: Bayes' rule leaves it as moved), is moved by the lidar odometry when given the scans: down a
    winding street, its path curving 0.004 / m more than the commands say, its mean stays within 0.5 m of
    the true path over 300 frames (the bilinear split keeps the mean exact), where the commands alone leave
    it more than 10 m off. Its heading spreads by what the odometry's own heading variance grows frame by
    frame (:func:`ego_motion.follow`'s covariances; nothing where a match narrows it): a random walk over the
    bins, whose variances add."""
    frames = 300
    model = odometry_model()  # the exact bicycle: no process noise moves the mean
    command = np.zeros((frames, 2), np.float32)
    command[:, 1] = 0.03 * np.sin(np.arange(frames) / 40.0)
    ds = np.full(frames, 0.6)  # 6 m/s, the pedal at 0
    dyaw = ds * np.asarray(motion.curvature(model, jnp.asarray(command[:, 1]), 6.0)) + 0.004 * ds
    xy, _, scans = street(ds, dyaw)
    grid = pose_belief.Grid(cell_m=5.0, heading_bins=36)
    origin = np.array([200.0, 200.0])
    start = jnp.asarray([[*origin, 1.0, 0.0, 6.0]], jnp.float32)
    flat = dict(
        place_logit=jnp.zeros((1, grid.num_cells)),
        place_offset=jnp.zeros((1, grid.num_cells, 2)),
        heading_logit=jnp.zeros((1, grid.heading_bins)),
        heading_offset=jnp.zeros((1, grid.heading_bins)),
        speed=jnp.full((1,), 0.6),
    )

    @functools.partial(jax.jit, static_argnums=0, compiler_options=OPTIMISED)  # 300 frames of the town's belief
    def track(with_scans):
        def body(state, x):
            action, scan, first = x
            state, _ = pose_belief.filter_step(
                state, flat, action[None], first[None], grid, model, start_pose=start, scan=scan, relocation=0.0
            )
            return state, pose_belief.mean_pose(state, grid)[0]

        actions = jnp.asarray(np.concatenate([command[:1], command]))  # frame t's: the commands t-1 -> t
        firsts = jnp.arange(frames + 1) == 0
        xs = (actions, scans[:, None] if with_scans else None, firsts)
        return jax.lax.scan(body, pose_belief.init_state(1, grid), xs)

    error_m = lambda poses: np.linalg.norm(np.asarray(poses[:, :2]) - origin - xy, axis=-1)
    last, poses = track(True)
    assert error_m(poses).max() < 0.5, error_m(poses).max()
    assert error_m(track(False)[1]).max() > 10.0  # the commands alone miss the offset

    heading_var_rad2 = np.asarray(_follow(model, 6.0, command, scans)[2])[:, 2, 2].astype(np.float64)
    grown = np.maximum(np.diff(heading_var_rad2), 0.0)
    assert np.any(np.diff(heading_var_rad2) < 0)  # matches narrowed it, and took nothing back from the belief
    p = np.asarray(last.belief[0], np.float64).sum((1, 2))  # [H]
    bins = np.arange(grid.heading_bins)
    spread_rad2 = np.sum(p * (bins - np.sum(p * bins)) ** 2) * grid.bin_rad**2
    np.testing.assert_allclose(spread_rad2, grown.sum(), rtol=1e-2)


def test_the_belief_covariance_is_the_error_covariance_with_the_location_scaled():
    """The belief's covariance is the odometry's error covariance with the location scaled by the fitted
    factor's root (D C D, D = diag(r, r, 1), r^2 the factor: the covariance of the errors so scaled), for a
    batch of random covariances, in NumPy float64 and in JAX; its diagonal keeps the heading's variance and
    scales the location's by the factor exactly."""
    rng = np.random.default_rng(5)
    a = rng.normal(size=(4, 3, 3)) * [2.0, 1.0, 0.01]
    covariance = a @ np.swapaxes(a, -1, -2)  # [4, 3, 3]
    model = dataclasses.replace(odometry_model(), odometry_location_scale=2.5)
    d = np.diag([np.sqrt(2.5), np.sqrt(2.5), 1.0])
    got = ego_motion.belief_covariance(covariance, model)
    np.testing.assert_allclose(got, d @ covariance @ d, rtol=1e-12)
    diagonal = lambda x: np.diagonal(x, 0, -2, -1)
    np.testing.assert_array_equal(diagonal(got), diagonal(covariance) * [2.5, 2.5, 1.0])
    in_jax = ego_motion.belief_covariance(jnp.asarray(covariance, jnp.float32), model)
    np.testing.assert_allclose(in_jax, d @ covariance @ d, rtol=1e-5)


def test_the_forward_precision_is_the_inverse_of_the_marginal_variance():
    """For any information matrix, the forward precision along a direction equals one over the forward
    variance that inverting the whole (the prior's precision on the motion across and the heading added,
    in the rotated axes) gives."""
    rng = np.random.default_rng(0)
    for _ in range(5):
        a = rng.normal(size=(3, 3)) * [10.0, 10.0, 200.0]
        information = a @ a.T
        angle = rng.uniform(-np.pi, np.pi)
        u = np.array([np.cos(angle), np.sin(angle)])
        basis = np.array([[u[0], u[1], 0.0], [-u[1], u[0], 0.0], [0.0, 0.0, 1.0]])
        rotated = basis @ information @ basis.T + np.diag([0.0, *np.asarray(ego_motion.PRIOR_STD[1:]) ** -2.0])
        truth = 1.0 / np.linalg.inv(rotated)[0, 0]
        found = float(ego_motion.forward_precision(jnp.asarray(information, jnp.float32), jnp.asarray(u, jnp.float32)))
        np.testing.assert_allclose(found, truth, rtol=1e-3)


def test_a_corridors_walls_do_not_pin_the_distance_and_a_cross_wall_does():
    """Two long walls either side of the car pin its motion across the road and its heading, not along it:
    the match's forward precision is under a hundredth of that across; a 14 m wall across the road ahead
    pins the distance (about a tenth as sharply as the two long walls, with ten times its returns, pin the
    motion across)."""
    walls = np.array([[0.0, 8.0, 0.0, 200.0, 1.0], [0.0, -8.0, 0.0, 200.0, 1.0]], np.float32)
    far = np.array([[300.0, 300.0, 0.0, 4.0, 4.0]], np.float32)  # (the scan casts a power of two of obstacles)
    cross = np.array([[25.0, 0.0, 0.0, 1.0, 14.0]], np.float32)
    for box, pinned in ((np.concatenate([walls, far, far]), False), (np.concatenate([walls, cross, far]), True)):
        before, after = lidar_scan(box, (0.0, 0.0, 0.0)), lidar_scan(box, (1.0, 0.0, 0.0))
        _, _, information = ego_motion.match(before, after, jnp.asarray([1.0, 0.0, 0.0]))
        along = float(ego_motion.forward_precision(information, jnp.asarray([1.0, 0.0])))
        across = float(ego_motion.forward_precision(information, jnp.asarray([0.0, 1.0])))
        assert (along > 0.05 * across) if pinned else (along < 0.01 * across)


def test_the_scan_matcher_follows_the_true_motion_on_a_town_it_never_saw():
    """On town 7, nearly every keyframe has enough returns, and its match is within 0.5 mrad of the world's
    true heading change at the median (on the tables' drives: 0.05 mrad) and almost never off by 5 mrad,
    though its prior is the exact bicycle, blind to the drive's steering offset."""
    cfg = config_lib.get_config("cpu")
    errors = calibration.scan_errors(cfg, motion.MotionModel(), 7, jax.random.PRNGKey(3), 2, 150)
    kept = errors.num_returns >= ego_motion.MIN_RETURNS
    assert kept.mean() > 0.9
    assert np.median(np.abs(errors.heading_rad[kept])) < 5e-4
    assert np.mean(np.abs(errors.heading_rad[kept]) > 5e-3) < 0.02


def test_a_motion_model_from_before_the_lidar_odometry_gains_its_prior_scan_noise_and_spread(tmp_path):
    """A run whose motion_model.json predates the lidar odometry (no offset or gain priors, no scan noises,
    no spread) gets them all fitted and saved the first time the odometry needs them; its own fields stay as they
    were."""
    cfg = config_lib.get_config("tiny")
    old = motion.MotionModel(lag_share=0.5, steer_gain=0.97, heading_noise_rad2pm=3e-4)
    old.save(str(tmp_path))
    model = calibration.ensure_scans(cfg, str(tmp_path))
    assert model.yaw_bias_std_1pm > 0 and model.yaw_gain_std > 0 and model.yaw_noise_rad2pm > 0
    assert model.speed_gain_std > 0 and model.speed_noise_mps > 0
    assert ego_motion.uses_distance(model) and ego_motion.spreads(model)
    assert model.chord_angle_noise_rad > 0 and model.odometry_heading_scale > 0
    fitted = dict(yaw_bias_std_1pm=0.0, yaw_gain_std=0.0, yaw_noise_rad2pm=0.0, scan_heading_noise_rad=0.0)
    fitted.update(speed_gain_std=0.0, speed_noise_mps=0.0, scan_distance_noise=0.0, chord_angle_noise_rad=0.0)
    fitted.update(odometry_heading_scale=1.0, odometry_location_scale=0.0)
    assert dataclasses.replace(model, **fitted) == old
    assert motion.MotionModel.load(str(tmp_path)) == model


@pytest.mark.parametrize("matcher", ["image", "heading", "distance"])
def test_a_motion_model_fitted_for_an_earlier_matcher_is_read_without_its_scan_noise_and_spread(tmp_path, matcher):
    """A motion_model.json saved when the matcher read the lidar image ("scan_yaw_noise_rad"), when the
    scans corrected the heading alone (no "scan_distance_noise"), or before the odometry carried its error
    covariance (no "chord_angle_noise_rad"; its spread a law of the distance driven), loads without the
    scans' noises and the spread, so that `calibration.ensure_scans` fits them for the odometry as it is;
    the motion model's own fields and the priors are kept."""
    kept = motion.MotionModel(lag_share=0.5, steer_gain=0.97, yaw_bias_std_1pm=0.0014, yaw_gain_std=0.034)
    fields = {k: v for k, v in dataclasses.asdict(kept).items() if not k.startswith(("scan_", "chord_", "odometry_"))}
    fields.update(odometry_location_std_at_100m_m=6.3, odometry_location_growth=1.54)
    if matcher == "image":
        fields.update(scan_yaw_noise_rad=0.047)
    elif matcher == "heading":
        fields.update(scan_heading_noise_rad=0.001)
    else:
        fields.update(scan_heading_noise_rad=0.001, scan_distance_noise=0.15)
    (tmp_path / motion.FILE_NAME).write_text(json.dumps(fields))
    loaded = motion.MotionModel.load(str(tmp_path))
    assert loaded == kept
    assert not ego_motion.uses_scans(loaded) and not ego_motion.spreads(loaded)


def test_the_error_covariance_carries_a_heading_error_across_the_motion():
    """A heading error of variance s^2 at the start, the car driving straight d metres at heading psi without
    scans (nothing adds to the covariance): the position's error is d times the heading's across the motion,
    so the covariance is s^2 [a; 1][a; 1]' with a = d (-sin psi, cos psi), and nothing along it."""
    model = motion.MotionModel()
    yaw, s2 = 0.3, 0.01**2
    start = jnp.asarray([[10.0, -5.0, np.cos(yaw), np.sin(yaw), 8.0]], jnp.float32)
    state = ego_motion.init_state(1)
    actuator, command = jnp.zeros((1, 2)), jnp.zeros((1, 2))
    first = jnp.ones((1,), bool)
    state, actuator, pose = ego_motion.step(state, model, actuator, command, start, None, first, start)
    state = state.replace(pose_covariance=state.pose_covariance.at[:, 2, 2].set(s2))
    for _ in range(40):
        state, actuator, pose = ego_motion.step(state, model, actuator, command, pose, None, ~first, start)
    d = float(np.linalg.norm(np.asarray(pose[0, :2] - start[0, :2])))
    assert d > 20.0  # it drove
    a = d * np.array([-np.sin(yaw), np.cos(yaw), 0.0]) + np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(np.asarray(state.pose_covariance[0]), s2 * np.outer(a, a), rtol=1e-4, atol=1e-9)
