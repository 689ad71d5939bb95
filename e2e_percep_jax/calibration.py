"""Fits the estimators' motion model (:class:`e2e_percep_jax.sim.motion.MotionModel`) on training drives, as a
car maker calibrates odometry: from logged commands and the true poses of drives, never from the plant.

:func:`training_drives` drives worlds of the training town from keys disjoint from the training batches'
and the evaluation's (ego commands, speed and pose each step, no sensors: seconds). :func:`fit` then

1. picks the actuator lag from a grid (the one whose lagged commands explain acceleration and curvature
   best), and for it fits by least squares the pedal's gain and bias, and the curvature's steering gain,
   bias and understeer term;
2. fits the process noise: for horizons of ``HORIZONS`` steps from every start, the heading error of the
   model's curvature integrated over the true distance, and the position error of the model's speed
   integrated along the true path; the per-metre variances are the largest ratio of mean squared error to
   mean distance over those horizons, so the belief covers the model's error up to the longest (per-drive
   parameters, a steering offset above all, make errors grow faster than a random walk's).
"""

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax import ego_motion
from e2e_percep_jax.config import Config, WorldConfig
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import motion, sensors, world
from e2e_percep_jax.sim import town as town_lib
from e2e_percep_jax.sim.geometry import wrap_angle
from e2e_percep_jax.sim.motion import DT_S, WHEELBASE_M, MotionModel

CALIBRATION_SEED = 999_983  # the drives' root key: not a training seed's batches, nor the evaluation's worlds
LAG_GRID_S = (0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4)
HORIZONS = (10, 30, 100, 300)  # steps
MIN_SPEED_MPS = 1.0  # slower steps are left out of the fits (curvature is ill-defined when standing)


@functools.partial(jax.jit, static_argnames=("world_cfg", "warmup_steps", "num_worlds", "num_steps", "scans"))
def drives(key, town, world_cfg: WorldConfig, warmup_steps: int, num_worlds: int, num_steps: int, scans: bool = False):
    """``num_worlds`` drives of ``num_steps`` steps after ``warmup_steps``, reset from ``key``; per step: the
    ego's (x m, y m, yaw rad) [W, T, 3], speed [W, T], the commands applied from it to the next [W, T, 2]
    and, with ``scans``, its lidar scan [W, T, A] (``sensors.render_scan``; else None)."""

    def one(k):
        def body(s, _):
            after = world.step(s, town)
            scan = sensors.observe_scan(s, town) if scans else None
            return after, (s.veh_box[world.EGO, :3], s.veh_speed_mps[world.EGO], after.ego_action, scan)

        # (one loop through the warm-up and the drive: the world's step is compiled once, not twice)
        drive = jax.lax.scan(body, world.reset(k, town, world_cfg), None, length=warmup_steps + num_steps)[1]
        return jax.tree.map(lambda x: x[warmup_steps:], drive)

    return jax.vmap(one)(jax.random.split(key, num_worlds))


def start_and_commands(pose, speed, command):
    """:func:`drives`' pose [W, T, 3], speed [W, T] and commands [W, T, 2] as a perceiver meets them: each
    drive's first pose [W, 5] (x, y, cos, sin, speed) and frame t's commands, those applied from t-1 to t
    [W, T, 2] (frame 0's: its own, which only set the actuators)."""
    yaw = pose[:, 0, 2]
    start = jnp.stack([pose[:, 0, 0], pose[:, 0, 1], jnp.cos(yaw), jnp.sin(yaw), speed[:, 0]], -1)
    return start, jnp.concatenate([command[:, :1], command[:, :-1]], 1)


def training_drives(cfg: Config, num_worlds: int = 8, num_steps: int = 1500) -> dict:
    """``num_worlds`` drives of ``num_steps`` steps in the training town after the traffic's warm-up, reset
    from ``PRNGKey(CALIBRATION_SEED)``. NumPy arrays [W, T]: ``pose`` [W, T, 3] (x m, y m, yaw rad),
    ``speed_mps``, ``command`` [W, T, 2] (the commands applied from step t to t + 1)."""
    # (on this process's own device: in a multi-process run the first device is another host's)
    with jax.default_device(jax.local_devices()[0]):
        key = jax.random.PRNGKey(CALIBRATION_SEED)
        town = town_lib.build_town(cfg.world.town_seed)
        # (the world and the warm-up alone are static: runs that differ in anything else share one compilation)
        driven = drives(key, town, cfg.world, cfg.data.warmup_steps, num_worlds, num_steps)
        pose, speed, command, _ = jax.tree.map(np.asarray, driven)
    return {
        "pose": pose.astype(np.float64),
        "speed_mps": speed.astype(np.float64),
        "command": command.astype(np.float64),
    }


def _lagged(command, share):
    """The commands [W, T, 2] through the lag: actuator state after each step, starting at the first command."""
    out, actuator = np.empty_like(command), command[:, 0]
    for t in range(command.shape[1]):
        actuator = out[:, t] = motion.lag_step(share, actuator, command[:, t])
    return out


def _least_squares(features, target):
    """(coefficients, mean squared residual) of target [M] ~ features [M, F]."""
    coef, *_ = np.linalg.lstsq(features, target, rcond=None)
    return coef, float(np.mean((features @ coef - target) ** 2))


def _rear_axle(pose):
    """The rear axle's position [..., 2] of centre poses [..., 3] (x, y, yaw)."""
    return pose[..., :2] - 0.5 * WHEELBASE_M * np.stack([np.cos(pose[..., 2]), np.sin(pose[..., 2])], -1)


def _steps(pose):
    """(rear axle [W, T, 2], its distance [W, T-1] and the yaw change [W, T-1] of each step) of poses [W, T, 3]."""
    rear = _rear_axle(pose)
    return rear, np.linalg.norm(np.diff(rear, axis=1), axis=-1), wrap_angle(np.diff(pose[..., 2], axis=1))


def fit(drives: dict) -> MotionModel:
    """The motion model of drives (:func:`training_drives`' arrays): see the module docstring."""
    pose, v, command = drives["pose"], drives["speed_mps"], drives["command"]
    accel = np.diff(v, axis=1) / DT_S  # [W, T-1]: step t's acceleration
    rear, ds, dyaw = _steps(pose)
    v_mid = 0.5 * (v[:, 1:] + v[:, :-1])
    moving = v_mid > MIN_SPEED_MPS
    best = None
    for lag_s in LAG_GRID_S:
        share = motion.lag_share(lag_s)
        actuator = _lagged(command, share)[:, :-1]  # step t's actuators
        pedal_features = np.stack([actuator[..., 0], np.ones_like(v_mid)], -1)[moving]
        pedal_coef, pedal_mse = _least_squares(pedal_features, accel[moving])
        tan = np.tan(actuator[..., 1])
        # WHEELBASE x curvature, weighted by distance (dyaw's noise is per step, so curvature's shrinks with ds)
        curve_features = np.stack([tan, np.ones_like(tan), tan * v_mid**2], -1)[moving] * ds[moving][:, None]
        curve_coef, curve_mse = _least_squares(curve_features, WHEELBASE_M * dyaw[moving])
        score = pedal_mse / np.var(accel[moving]) + curve_mse / np.var(WHEELBASE_M * dyaw[moving])
        if best is None or score < best[0]:
            best = (score, share, pedal_coef, curve_coef)
    _, share, pedal_coef, curve_coef = best
    model = MotionModel(
        lag_share=float(share),
        accel_per_pedal_mps2=float(pedal_coef[0]),
        accel_bias_mps2=float(pedal_coef[1]),
        steer_gain=float(curve_coef[0]),
        steer_bias=float(curve_coef[1]),
        understeer_s2pm2=float(curve_coef[2]),
    )
    return _with_drive_spread(_with_process_noise(model, drives, rear, ds, dyaw), drives, ds, dyaw)


def _with_process_noise(model: MotionModel, drives: dict, rear, ds, dyaw) -> MotionModel:
    v, command = drives["speed_mps"], drives["command"]
    actuator = _lagged(command, model.lag_share)[:, :-1]
    v_mid = 0.5 * (v[:, 1:] + v[:, :-1])
    model_dyaw = ds * np.asarray(motion.curvature(model, actuator[..., 1], v_mid))
    # The model's own speed from each step's true speed: the distance it would drive.
    _, model_ds = (np.asarray(x) for x in motion.speed_and_distance(model, actuator, v[:, :-1]))
    heading_ratio, position_ratio = 0.0, 0.0
    yaw = drives["pose"][:, :-1, 2]
    for h in HORIZONS:
        if h >= ds.shape[1]:
            continue
        cum = lambda x: np.concatenate([np.zeros((x.shape[0], 1)), np.cumsum(x, 1)], 1)
        dist = cum(ds)[:, h:] - cum(ds)[:, :-h]  # [W, S]: distance over each horizon
        heading_err = (cum(dyaw) - cum(model_dyaw))[:, h:] - (cum(dyaw) - cum(model_dyaw))[:, :-h]
        # Position: the model's distance along the true headings, against the true rear-axle path.
        step_xy = (model_ds - ds)[..., None] * np.stack([np.cos(yaw), np.sin(yaw)], -1)
        along = np.concatenate([np.zeros((step_xy.shape[0], 1, 2)), np.cumsum(step_xy, 1)], 1)
        position_err = along[:, h:] - along[:, :-h]
        keep = dist > 1.0
        heading_ratio = max(heading_ratio, np.mean(heading_err[keep] ** 2) / np.mean(dist[keep]))
        position_ratio = max(position_ratio, 0.5 * np.mean(np.sum(position_err[keep] ** 2, -1)) / np.mean(dist[keep]))
    return dataclasses.replace(
        model, heading_noise_rad2pm=float(heading_ratio), position_noise_m2pm=float(position_ratio)
    )


def _with_drive_spread(model: MotionModel, drives: dict, ds, dyaw) -> MotionModel:
    """The lidar odometry's priors: per drive, the least-squares curvature bias and yaw gain error of the
    model's yaw changes (``dyaw - model_dyaw ~ bias * ds + gain_error * model_dyaw``) and the acceleration
    gain error of its accelerations (``accel - model_accel ~ gain_error * model_accel``); their root mean
    square over drives, and the residuals' variance (per metre for the yaw, a step's speed for the speed)."""
    actuator = _lagged(drives["command"], model.lag_share)[:, :-1]
    v = drives["speed_mps"]
    model_dyaw = ds * np.asarray(motion.curvature(model, actuator[..., 1], 0.5 * (v[:, 1:] + v[:, :-1])))
    accel = np.diff(v, axis=1) / DT_S
    model_accel = np.asarray(motion.acceleration(model, actuator), np.float64)
    yaw_fits, yaw_residuals, speed_fits, speed_residuals = [], [], [], []
    for w in range(ds.shape[0]):
        moving = ds[w] > MIN_SPEED_MPS * DT_S
        features = np.stack([ds[w], model_dyaw[w]], -1)[moving]
        coef, mse = _least_squares(features, (dyaw - model_dyaw)[w][moving])
        yaw_fits.append(coef)
        yaw_residuals.append(mse / np.mean(ds[w][moving]))
        coef, mse = _least_squares(model_accel[w][moving][:, None], (accel - model_accel)[w][moving])
        speed_fits.append(coef[0])
        speed_residuals.append(mse * DT_S**2)
    bias_std, gain_std = np.sqrt(np.mean(np.square(yaw_fits), 0))
    return dataclasses.replace(
        model,
        yaw_bias_std_1pm=float(bias_std),
        yaw_gain_std=float(gain_std),
        yaw_noise_rad2pm=float(np.mean(yaw_residuals)),
        speed_gain_std=float(np.sqrt(np.mean(np.square(speed_fits)))),
        speed_noise_mps=float(np.sqrt(np.mean(speed_residuals))),
    )


def lidar_drives(cfg: Config, town_seed: int, key, num_worlds: int, num_frames: int):
    """:func:`drives` of town ``town_seed`` under ``cfg``'s world, with its lidar scans, on the first
    local device."""
    with jax.default_device(jax.local_devices()[0]):
        town = town_lib.build_town(town_seed)
        return drives(key, town, cfg.world, cfg.data.warmup_steps, num_worlds, num_frames, scans=True)


class ScanErrors(NamedTuple):
    """:func:`scan_errors`' matches [M]: the heading change's error (rad), the forward motion's error along
    the predicted chord (m) and its precision from the match (:func:`ego_motion.forward_precision`), the
    model's own lateral error (the true motion across its predicted chord, m), the true chord (m), and the
    fewer of each pair's returns."""

    heading_rad: np.ndarray
    forward_m: np.ndarray
    forward_precision: np.ndarray
    model_lateral_m: np.ndarray
    chord_m: np.ndarray
    num_returns: np.ndarray


def scan_errors(cfg: Config, model: MotionModel, town_seed: int, key, num_worlds: int = 4, num_frames: int = 300):
    """The scan matcher's errors on ``num_worlds`` lidar drives of town ``town_seed`` (reset from ``key``):
    every ``ego_motion.KEYFRAME_FRAMES`` frames, the matched motion against the true one, searched around
    the motion ``model``'s own prediction from the true pose and speed (:class:`ScanErrors`)."""
    pose, speed, command, scan = lidar_drives(cfg, town_seed, key, num_worlds, num_frames)
    k = ego_motion.KEYFRAME_FRAMES
    starts = np.arange(0, num_frames - k, k)
    predicted = []
    for start in starts:  # the model's motion over each interval, from the true pose
        local = jnp.zeros((num_worlds, 5)).at[:, 2].set(1.0).at[:, 4].set(speed[:, start])
        actuator = command[:, start]
        for t in range(start, start + k):
            actuator, local = motion.advance_pose(model, actuator, command[:, t], local)
        predicted.append(jnp.concatenate([local[:, :2], jnp.arctan2(local[:, 3:4], local[:, 2:3])], -1))
    predicted = jnp.stack(predicted, 1).reshape(-1, 3)
    pairs = lambda x, offset: x[:, starts + offset].reshape((-1,) + x.shape[2:])
    measured, num_returns, information = jax.jit(jax.vmap(ego_motion.match))(pairs(scan, 0), pairs(scan, k), predicted)
    pose = np.asarray(pose, np.float64)
    before, after = pairs(pose, 0), pairs(pose, k)
    true_xy = np.asarray(geo.town_to_ego(after[:, :2], before[:, :2], before[:, 2]))
    chord = np.linalg.norm(np.asarray(predicted[:, :2], np.float64), axis=-1)
    ahead = np.where(chord[:, None] > 1e-3, np.asarray(predicted[:, :2]) / np.maximum(chord, 1e-3)[:, None], [1.0, 0.0])
    across = np.stack([-ahead[:, 1], ahead[:, 0]], -1)
    return ScanErrors(
        heading_rad=wrap_angle(np.asarray(measured[:, 2]) - wrap_angle(after[:, 2] - before[:, 2])),
        forward_m=np.sum((np.asarray(measured[:, :2], np.float64) - true_xy) * ahead, -1),
        forward_precision=np.asarray(ego_motion.forward_precision(information, jnp.asarray(ahead, jnp.float32))),
        model_lateral_m=-np.sum(true_xy * across, -1),
        chord_m=np.linalg.norm(true_xy, axis=-1),
        num_returns=np.asarray(num_returns),
    )


def fit_scans(cfg: Config, model: MotionModel) -> MotionModel:
    """``model`` with the scan matcher's noises (:mod:`e2e_percep_jax.ego_motion`), fitted on lidar drives of
    the training town from a key of their own (:func:`scan_errors`), over matches with at least
    ``ego_motion.MIN_RETURNS`` returns: the heading's, the errors' robust spread (1.4826 times the median
    absolute error) times the square root of the scans' returns; the forward motion's, the robust spread of
    its errors times the square root of their precision, over matches that moved (a standing car's match
    is exact, and would shrink the spread); and the motion model's own error across its chord, as an angle
    (the robust spread of its lateral error over the chord), which the odometry's error covariance carries."""
    key = jax.random.fold_in(jax.random.PRNGKey(CALIBRATION_SEED), 1)
    errors = scan_errors(cfg, model, cfg.world.town_seed, key)
    kept = errors.num_returns >= ego_motion.MIN_RETURNS
    heading = 1.4826 * np.median(np.abs(errors.heading_rad[kept]) * np.sqrt(errors.num_returns[kept]))
    moved = kept & (errors.chord_m > MIN_SPEED_MPS * DT_S * ego_motion.KEYFRAME_FRAMES)
    robust = lambda x: float(1.4826 * np.median(np.abs(x[moved])))
    return dataclasses.replace(
        model,
        scan_heading_noise_rad=float(heading),
        scan_distance_noise=robust(errors.forward_m * np.sqrt(errors.forward_precision)),
        chord_angle_noise_rad=robust(errors.model_lateral_m / np.maximum(errors.chord_m, 1e-9)),
    )


CHI2_95 = {1: 3.8415, 2: 5.9915, 3: 7.8147}  # chi-square's 95 % quantile with 1, 2 and 3 degrees of freedom
MOVED_M = 1.0  # frames before the car has driven this far from its known start are left out of the spread's fit


def squared_errors(error, covariance):
    """The squared Mahalanobis distances [...] of errors [..., k] under covariances [..., k, k]."""
    return np.einsum("...i,...i->...", error, np.linalg.solve(covariance, error[..., None])[..., 0])


def spread_errors(pose, followed, covariance):
    """The odometry's errors under its error covariance on drives from a known start: the squared
    Mahalanobis distances of the location errors [W, T] (under ``covariance[..., :2, :2]``), of the heading
    errors [W, T] and of both [W, T] (under the whole covariance), for true poses [W, T, 3] (x, y, yaw),
    ``followed`` poses [W, T, 5] and covariances [W, T, 3, 3] (``ego_motion.follow``); NaN on frames before
    the car has driven MOVED_M (the covariance is ~0)."""
    pose, followed, covariance = (np.asarray(x, np.float64) for x in (pose, followed, covariance))
    step_m = np.linalg.norm(np.diff(pose[:, :, :2], axis=1), axis=-1)
    moved = np.concatenate([np.zeros((pose.shape[0], 1)), np.cumsum(step_m, 1)], 1) > MOVED_M
    yaw_error = wrap_angle(np.arctan2(followed[..., 3], followed[..., 2]) - pose[..., 2])
    error = np.concatenate([followed[..., :2] - pose[..., :2], yaw_error[..., None]], -1)[moved]
    location, heading, joint = (np.full(moved.shape, np.nan) for _ in range(3))
    location[moved] = squared_errors(error[:, :2], covariance[moved][:, :2, :2])
    heading[moved] = error[:, 2] ** 2 / covariance[moved][:, 2, 2]
    joint[moved] = squared_errors(error, covariance[moved])
    return location, heading, joint


def spread_scale(squared_distance, dims: int) -> float:
    """The factor on a covariance that puts 95 % of the errors, whose squared Mahalanobis distances under it
    are ``squared_distance`` [M] (NaN: left out), inside its 95 % region (an ellipse in ``dims`` dimensions)."""
    return float(np.nanquantile(squared_distance, 0.95) / CHI2_95[dims])


def fit_spread(cfg: Config, model: MotionModel) -> MotionModel:
    """``model`` with the odometry's spread: ``cfg.eval.spread_drives_per_town`` lidar drives of
    ``cfg.eval.spread_frames`` frames in each of ``cfg.eval.spread_town_seeds`` from a key of their own, followed
    from their true starts by the odometry
    (``ego_motion.follow``: with the scans when ``model`` has the matcher's noise); the factor on its error
    covariance's heading variances that holds 95 % of the heading errors in the 95 % interval, then, with
    the heading's variances so scaled (which moves the position's), the factor on the location's that holds
    95 % of the location errors in the 95 % ellipse (:func:`spread_scale`; frames after the first MOVED_M).
    The belief reads the spread only on towns its place head never saw, so it is fitted on such towns: the
    training town's streets hold the odometry tighter (on the `cpu` preset's, a third of the error of towns
    1, 2, 7 and 8)."""
    drives = []
    for town_seed in cfg.eval.spread_town_seeds:
        key = jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(CALIBRATION_SEED), 2), town_seed)
        pose, speed, command, scan = lidar_drives(
            cfg, town_seed, key, cfg.eval.spread_drives_per_town, cfg.eval.spread_frames
        )
        drives.append((pose, *start_and_commands(pose, speed, command), scan))

    def errors(model):
        """(squared location errors, squared heading errors) under ``model``'s error covariance, all drives."""
        squared = [
            spread_errors(pose, *jax.jit(ego_motion.follow, static_argnums=0)(model, start, prev_action, scan)[::2])
            for pose, start, prev_action, scan in drives
        ]
        return [np.concatenate([s[i].ravel() for s in squared]) for i in (0, 1)]

    model = dataclasses.replace(model, odometry_heading_scale=1.0)
    model = dataclasses.replace(model, odometry_heading_scale=spread_scale(errors(model)[1], 1))
    return dataclasses.replace(model, odometry_location_scale=spread_scale(errors(model)[0], 2))


def calibrate(cfg: Config, scans: bool = False, **drive_kwargs) -> MotionModel:
    """The motion model of ``cfg``'s world, fitted on :func:`training_drives`; with ``scans``, also the scan
    matcher's noise (:func:`fit_scans`) and the odometry's spread (:func:`fit_spread`), which only the lidar
    odometry reads."""
    model = fit(training_drives(cfg, **drive_kwargs))
    return fit_spread(cfg, fit_scans(cfg, model)) if scans else model


def ensure_scans(cfg: Config, workdir: str, spread: bool = True) -> MotionModel:
    """Run ``workdir``'s motion model with the scan matcher's noise (:func:`fit_scans`, seconds) and, with
    ``spread``, the odometry's spread (:func:`fit_spread`, a few minutes: only the pose of a town the head
    does not know needs it), fitted and saved into the run the first time the lidar odometry needs them."""
    model = MotionModel.load(workdir)
    if not ego_motion.uses_distance(model):
        print("fitting the scan matcher's noise on training drives", flush=True)
        if model.yaw_bias_std_1pm == 0 or model.speed_gain_std == 0:  # fitted before the odometry's priors
            drives = training_drives(cfg)
            _, ds, dyaw = _steps(drives["pose"])
            model = _with_drive_spread(model, drives, ds, dyaw)
        model = fit_scans(cfg, model)
        model.save(workdir)
    if spread and not ego_motion.spreads(model):
        print("fitting the odometry's spread on drives of other towns", flush=True)
        model = fit_spread(cfg, model)
        model.save(workdir)
    return model
