"""The lidar odometry (e2e_percep_jax/ego_motion.py): the scan matcher against known motions and the world's
true motion on a town the model never saw, its Kalman update against brute-force Bayes, and the drive's
steering offset learnt from scans of a drive with a planted one."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from e2e_percep_jax import calibration, ego_motion
from e2e_percep_jax import config as config_lib
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import motion, sensors


def _buildings(centres_m, rng):
    """Obstacles: boxes of 3-8 m sides and random yaw at town points ``centres_m`` [M, 2]."""
    m = len(centres_m)
    box = np.column_stack([centres_m, rng.uniform(-np.pi, np.pi, m), rng.uniform(3, 8, (m, 2))]).astype(np.float32)
    return box


def _scan(box_town, pose):
    """The lidar scan of buildings ``box_town`` [M, 5] (the nearest SCAN_BUILDINGS of them, as the sensors
    cull) from ego pose (x, y, yaw)."""
    box = geo.box_to_ego(jnp.asarray(box_town), jnp.asarray(pose[:2], jnp.float32), jnp.float32(pose[2]))
    m = min(box.shape[0], sensors.SCAN_BUILDINGS)
    box = box[jnp.argsort(jnp.linalg.norm(box[:, :2], axis=-1))[:m]]
    obstacles = sensors.Obstacles(
        box=box,
        height_m=jnp.full((m,), 6.0),
        color=jnp.zeros((m, 3)),
        is_vehicle=jnp.zeros((m,), bool),
        valid=jnp.ones((m,), bool),
        vehicle_index=jnp.full((m,), -1, jnp.int32),
    )
    return sensors.render_scan(obstacles)


def _town_block(seed):
    rng = np.random.default_rng(seed)
    box = _buildings(rng.uniform(-40, 40, (30, 2)), rng)
    return box[np.linalg.norm(box[:, :2], axis=-1) > 7]  # none over the ego


def test_the_scan_holds_the_lidars_walls_and_not_its_ground():
    """A world whose one building lies beyond the lidar's range has no return in its scan (the ground's are
    below the band); a wall 10 m ahead, 40 m wide, is at 10 / cos(azimuth) m in every azimuth that meets
    it, exactly."""
    assert ego_motion.SCAN_AZIMUTHS == sensors.LIDAR_NUM_AZIMUTHS
    far = np.array([[sensors.LIDAR_RANGE_M + 5.0, 0.0, 0.0, 4.0, 4.0]], np.float32)
    assert not np.any(np.asarray(_scan(far, (0.0, 0.0, 0.0))))
    wall = np.array([[10.5, 0.0, 0.0, 1.0, 40.0]], np.float32)  # its near face at x = 10 m
    scan = np.asarray(_scan(wall, (0.0, 0.0, 0.0)))
    azimuth = np.deg2rad(np.arange(360.0))
    meets = (np.cos(azimuth) > 0) & (np.abs(10.0 * np.tan(azimuth)) < 19.9)  # (off its ends by a margin)
    np.testing.assert_allclose(scan[meets], 10.0 / np.cos(azimuth[meets]), rtol=1e-5)
    assert not np.any(scan[np.cos(azimuth) < 0])  # nothing behind


@pytest.mark.parametrize("motion_true", [(1.0, 0.2, 0.03), (0.6, -0.1, -0.05), (1.5, 0.0, 0.0)])
def test_a_known_motion_between_two_scans_is_recovered_exactly(motion_true):
    """Two scans of the same buildings from poses a known motion apart: the match from a prior off by more
    than the motion model errs over a keyframe interval (0.15 m, 0.1 m, 0.02 rad) recovers the motion to
    5 mm and 0.2 mrad (4 mm at 20 m: the line through two returns cuts a building's corners; the prior's
    weak pull included)."""
    box = _town_block(1)
    before, after = _scan(box, (0.0, 0.0, 0.0)), _scan(box, motion_true)
    found, num_returns = ego_motion.match(before, after, jnp.asarray(motion_true) + jnp.asarray([0.15, -0.1, 0.02]))
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


def test_a_planted_steering_offset_is_learnt_from_the_scans_of_a_street():
    """A car whose path curves by a planted 0.004 / m more than its motion model says (a 0.6 degree
    steering offset) drives 600 frames down a street of buildings that follow its true path; the odometry
    learns the offset within 10 % and loses under a tenth of the heading that dead reckoning loses."""
    bias_1pm, frames, speed_mps = 0.004, 600, 6.0
    model = motion.MotionModel(
        yaw_bias_std_1pm=0.004, yaw_gain_std=0.03, yaw_noise_rad2pm=1e-7, scan_heading_noise_rad=0.002
    )
    command = np.zeros((frames, 2), np.float32)
    command[:, 1] = 0.03 * np.sin(np.arange(frames) / 40.0)  # a winding road
    ds = speed_mps * motion.DT_S
    model_dyaw = ds * np.asarray(motion.curvature(model, jnp.asarray(command[:, 1]), speed_mps))
    yaw = np.concatenate([[0.0], np.cumsum(model_dyaw + bias_1pm * ds)])
    xy = np.concatenate(
        [
            np.zeros((1, 2)),
            np.cumsum(
                np.asarray(motion.centre_move(np.full(frames, ds), model_dyaw + bias_1pm * ds, yaw[:-1, None]))[:, 0], 0
            ),
        ]
    )
    rng = np.random.default_rng(2)
    side = np.stack([-np.sin(yaw), np.cos(yaw)], -1)
    along = np.arange(0, frames + 1, 12)  # a building each side every 7 m
    centres = np.concatenate([xy[along] + 10 * side[along], xy[along] - 11 * side[along]])
    box = _buildings(centres + rng.normal(0, 1.0, centres.shape), rng)
    scans = jax.vmap(lambda p: _scan(box, p))(jnp.asarray(np.column_stack([xy, yaw]), jnp.float32))
    start = jnp.asarray([[0.0, 0.0, 1.0, 0.0, speed_mps]], jnp.float32)

    previous = jnp.asarray(np.concatenate([command[:1], command]))[None]  # frame t's: the commands t-1 -> t
    run = lambda m: jax.tree.map(
        lambda x: x[0], jax.jit(ego_motion.follow, static_argnums=0)(m, start, previous, scans[None])
    )
    poses, corrections = run(model)
    reckoned, _ = run(dataclasses.replace(model, scan_heading_noise_rad=0.0))
    assert abs(float(corrections[-1, 0]) - bias_1pm) < 0.1 * bias_1pm
    heading_error = lambda p: abs(float(geo.wrap_angle(geo.pose_yaw(p[-1]) - yaw[-1])))
    assert heading_error(reckoned) > 0.9 * bias_1pm * ds * frames  # dead reckoning misses all of it
    assert heading_error(poses) < 0.1 * heading_error(reckoned)


def test_the_scan_matcher_follows_the_true_motion_on_a_town_it_never_saw():
    """On town 7, nearly every keyframe has enough returns, and its match is within 0.5 mrad of the world's
    true heading change at the median (on the tables' drives: 0.05 mrad) and almost never off by 5 mrad,
    though its prior is the exact bicycle, blind to the drive's steering offset."""
    cfg = config_lib.get_config("cpu")
    error, num_returns = calibration.scan_errors(cfg, motion.MotionModel(), 7, jax.random.PRNGKey(3), 2, 150)
    kept = num_returns >= ego_motion.MIN_RETURNS
    assert kept.mean() > 0.9
    assert np.median(np.abs(error[kept])) < 5e-4
    assert np.mean(np.abs(error[kept]) > 5e-3) < 0.02


def test_a_motion_model_from_before_the_lidar_odometry_gains_its_prior_scan_noise_and_spread(tmp_path):
    """A run whose motion_model.json predates the lidar odometry (no offset prior, no scan noise, no spread)
    gets all three fitted and saved the first time the odometry needs them; its own fields stay as they
    were. The spread grows with the distance driven."""
    cfg = config_lib.get_config("tiny")
    old = motion.MotionModel(lag_share=0.5, steer_gain=0.97, heading_noise_rad2pm=3e-4)
    old.save(str(tmp_path))
    model = calibration.ensure_scans(cfg, str(tmp_path))
    assert model.yaw_bias_std_1pm > 0 and model.yaw_gain_std > 0 and model.yaw_noise_rad2pm > 0
    assert ego_motion.uses_scans(model) and ego_motion.spreads(model)
    assert model.odometry_location_growth > 0 and model.odometry_heading_std_at_100m_rad > 0
    fitted = dict(yaw_bias_std_1pm=0.0, yaw_gain_std=0.0, yaw_noise_rad2pm=0.0, scan_heading_noise_rad=0.0)
    fitted.update(odometry_location_std_at_100m_m=0.0, odometry_heading_std_at_100m_rad=0.0)
    fitted.update(odometry_location_growth=1.0, odometry_heading_growth=1.0)
    assert dataclasses.replace(model, **fitted) == old
    assert motion.MotionModel.load(str(tmp_path)) == model


def test_a_motion_model_fitted_for_the_image_matcher_is_read_without_its_scan_noise_and_spread(tmp_path):
    """A motion_model.json saved when the matcher read the lidar image ("scan_yaw_noise_rad", and a spread
    fitted with that odometry) loads with neither, so that `calibration.ensure_scans` fits both for the
    scans; the motion model's own fields and the offset's prior are kept."""
    kept = motion.MotionModel(lag_share=0.5, steer_gain=0.97, yaw_bias_std_1pm=0.0014, yaw_gain_std=0.034)
    fields = dataclasses.asdict(kept)
    del fields["scan_heading_noise_rad"]
    fields.update(scan_yaw_noise_rad=0.047, odometry_location_std_at_100m_m=6.3, odometry_location_growth=1.54)
    (tmp_path / motion.FILE_NAME).write_text(json.dumps(fields))
    loaded = motion.MotionModel.load(str(tmp_path))
    assert loaded == kept
    assert not ego_motion.uses_scans(loaded) and not ego_motion.spreads(loaded)
