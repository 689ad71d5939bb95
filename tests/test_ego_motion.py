"""The lidar odometry (e2e_percep_jax/ego_motion.py): the scan matcher against known motions and the world's
true motion on a town the model never saw, its Kalman update against brute-force Bayes, and the drive's
steering offset learnt from scans of a drive with a planted one."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from e2e_percep_jax import calibration, ego_motion
from e2e_percep_jax import config as config_lib
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import motion, sensors

R = 64
RES_M = geo.bev_metres_per_px(R)


def _lidar_of(mask):
    """A lidar image whose green channel holds ``mask`` [R, R] (and red ground rings the matcher must ignore)."""
    image = np.zeros((R, R, 3), np.uint8)
    image[..., 1] = 255 * mask
    rows, cols = np.mgrid[:R, :R]
    image[..., 0] = 255 * ((np.hypot(rows - R * 20 / 32, cols - R / 2) % 6) < 1)  # rings around the ego
    return jnp.asarray(image)


def _buildings(centres_m, rng):
    """Obstacles: boxes of 3-8 m sides and random yaw at town points ``centres_m`` [M, 2]."""
    m = len(centres_m)
    box = np.column_stack([centres_m, rng.uniform(-np.pi, np.pi, m), rng.uniform(3, 8, (m, 2))]).astype(np.float32)
    return box


def _render(box_town, pose):
    """The lidar image of buildings ``box_town`` [M, 5] (the nearest LIDAR_BUILDINGS of them, as the
    sensors cull) from ego pose (x, y, yaw)."""
    box = geo.box_to_ego(jnp.asarray(box_town), jnp.asarray(pose[:2], jnp.float32), jnp.float32(pose[2]))
    m = min(box.shape[0], sensors.LIDAR_BUILDINGS)
    box = box[jnp.argsort(jnp.linalg.norm(box[:, :2], axis=-1))[:m]]
    obstacles = sensors.Obstacles(
        box=box,
        height_m=jnp.full((m,), 6.0),
        color=jnp.zeros((m, 3)),
        is_vehicle=jnp.zeros((m,), bool),
        valid=jnp.ones((m,), bool),
        vehicle_index=jnp.full((m,), -1, jnp.int32),
    )
    return sensors.render_lidar(obstacles, R)[0]


def test_a_whole_pixel_shift_is_recovered_to_a_centimetre_whatever_the_ground_rings():
    rng = np.random.default_rng(0)
    mask = np.zeros((R, R), np.uint8)
    for _ in range(12):  # short wall segments
        r, c = rng.integers(8, R - 8, 2)
        if rng.random() < 0.5:
            mask[r, c : c + rng.integers(3, 8)] = 1
        else:
            mask[r : r + rng.integers(3, 8), c] = 1
    rows, cols = 3, -2  # the scene moves 3 pixels down and 2 left: the car drove 1.5 m ahead and 1 m right
    shifted = np.zeros_like(mask)
    shifted[rows:, : R + cols] = mask[: R - rows, -cols:]
    points, weight = ego_motion.scan_points(_lidar_of(mask))
    found, num_returns = ego_motion.match(points, weight, _lidar_of(shifted), jnp.asarray([1.2, -0.8, 0.02]))
    np.testing.assert_allclose(np.asarray(found)[:2], [rows * RES_M, cols * RES_M], atol=0.01)
    assert abs(float(found[2])) < 0.002
    assert num_returns == min(mask.sum(), shifted.sum())


@pytest.mark.parametrize("motion_true", [(1.0, 0.2, 0.03), (0.6, -0.1, -0.05)])
def test_a_rendered_turn_is_recovered_within_a_fifth_of_a_pixel_at_the_views_edge(motion_true):
    rng = np.random.default_rng(1)
    box = _buildings(rng.uniform(-25, 25, (14, 2)), rng)
    box = box[np.linalg.norm(box[:, :2], axis=-1) > 7]  # none over the ego
    before, after = _render(box, (0.0, 0.0, 0.0)), _render(box, motion_true)
    points, weight = ego_motion.scan_points(before)
    found, _ = ego_motion.match(points, weight, after, jnp.zeros(3))
    np.testing.assert_allclose(np.asarray(found)[:2], motion_true[:2], atol=0.2 * RES_M)
    assert abs(float(found[2]) - motion_true[2]) < 0.2 * RES_M / geo.BEV_SIDE_M


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
        yaw_bias_std_1pm=0.004, yaw_gain_std=0.03, yaw_noise_rad2pm=1e-7, scan_yaw_noise_rad=0.05
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
    lidar = jax.vmap(lambda p: _render(box, p))(jnp.asarray(np.column_stack([xy, yaw]), jnp.float32))
    start = jnp.asarray([[0.0, 0.0, 1.0, 0.0, speed_mps]], jnp.float32)

    previous = jnp.asarray(np.concatenate([command[:1], command]))[None]  # frame t's: the commands t-1 -> t
    run = lambda m: jax.tree.map(
        lambda x: x[0], jax.jit(ego_motion.follow, static_argnums=0)(m, start, previous, lidar[None])
    )
    poses, corrections = run(model)
    reckoned, _ = run(dataclasses.replace(model, scan_yaw_noise_rad=0.0))
    assert abs(float(corrections[-1, 0]) - bias_1pm) < 0.1 * bias_1pm
    heading_error = lambda p: abs(float(geo.wrap_angle(geo.pose_yaw(p[-1]) - yaw[-1])))
    assert heading_error(reckoned) > 0.9 * bias_1pm * ds * frames  # dead reckoning misses all of it
    assert heading_error(poses) < 0.1 * heading_error(reckoned)


def test_the_scan_matcher_follows_the_true_motion_on_a_town_it_never_saw():
    """On town 7, keyframe matches with enough returns are within 0.01 rad of the world's true heading change
    at the median, and almost never off by 0.05 rad."""
    cfg = config_lib.get_config("cpu")
    error, num_returns = calibration.scan_errors(cfg, motion.MotionModel(), 7, jax.random.PRNGKey(3), 2, 150)
    kept = num_returns >= ego_motion.MIN_RETURNS
    assert kept.mean() > 0.5
    assert np.median(np.abs(error[kept])) < 0.01
    assert np.mean(np.abs(error[kept]) > 0.05) < 0.1


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
    fitted = dict(yaw_bias_std_1pm=0.0, yaw_gain_std=0.0, yaw_noise_rad2pm=0.0, scan_yaw_noise_rad=0.0)
    fitted.update(odometry_location_std_at_100m_m=0.0, odometry_heading_std_at_100m_rad=0.0)
    fitted.update(odometry_location_growth=1.0, odometry_heading_growth=1.0)
    assert dataclasses.replace(model, **fitted) == old
    assert motion.MotionModel.load(str(tmp_path)) == model
