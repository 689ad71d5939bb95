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

import jax
import numpy as np

from e2e_percep_jax.config import Config, WorldConfig
from e2e_percep_jax.sim import motion, world
from e2e_percep_jax.sim import town as town_lib
from e2e_percep_jax.sim.geometry import wrap_angle
from e2e_percep_jax.sim.motion import DT_S, WHEELBASE_M, MotionModel

CALIBRATION_SEED = 999_983  # the drives' root key: not a training seed's batches, nor the evaluation's worlds
LAG_GRID_S = (0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4)
HORIZONS = (10, 30, 100, 300)  # steps
MIN_SPEED_MPS = 1.0  # slower steps are left out of the fits (curvature is ill-defined when standing)


@functools.partial(jax.jit, static_argnames=("world_cfg", "warmup_steps", "num_worlds", "num_steps"))
def _drive(key, town, world_cfg: WorldConfig, warmup_steps: int, num_worlds: int, num_steps: int):
    def one(k):
        def body(s, _):
            after = world.step(s, town)
            return after, (s.veh_box[world.EGO, :3], s.veh_speed_mps[world.EGO], after.ego_action)

        # (one loop through the warm-up and the drive: the world's step is compiled once, not twice)
        drive = jax.lax.scan(body, world.reset(k, town, world_cfg), None, length=warmup_steps + num_steps)[1]
        return jax.tree.map(lambda x: x[warmup_steps:], drive)

    return jax.vmap(one)(jax.random.split(key, num_worlds))


def training_drives(cfg: Config, num_worlds: int = 8, num_steps: int = 1500) -> dict:
    """``num_worlds`` drives of ``num_steps`` steps in the training town after the traffic's warm-up, reset
    from ``PRNGKey(CALIBRATION_SEED)``. NumPy arrays [W, T]: ``pose`` [W, T, 3] (x m, y m, yaw rad),
    ``speed_mps``, ``command`` [W, T, 2] (the commands applied from step t to t + 1)."""
    # (on this process's own device: in a multi-process run the first device is another host's)
    with jax.default_device(jax.local_devices()[0]):
        key = jax.random.PRNGKey(CALIBRATION_SEED)
        town = town_lib.build_town(cfg.world.town_seed)
        # (the world and the warm-up alone are static: runs that differ in anything else share one compilation)
        drives = _drive(key, town, cfg.world, cfg.data.warmup_steps, num_worlds, num_steps)
        pose, speed, command = jax.tree.map(np.asarray, drives)
    return {
        "pose": pose.astype(np.float64),
        "speed_mps": speed.astype(np.float64),
        "command": command.astype(np.float64),
    }


def _lagged(command, share):
    """The commands [W, T, 2] through the lag: actuator state after each step, starting at the first command."""
    out, actuator = np.empty_like(command), command[:, 0]
    for t in range(command.shape[1]):
        actuator = actuator + share * (command[:, t] - actuator)
        out[:, t] = actuator
    return out


def _least_squares(features, target):
    """(coefficients, mean squared residual) of target [M] ~ features [M, F]."""
    coef, *_ = np.linalg.lstsq(features, target, rcond=None)
    return coef, float(np.mean((features @ coef - target) ** 2))


def _rear_axle(pose):
    """The rear axle's position [..., 2] of centre poses [..., 3] (x, y, yaw)."""
    return pose[..., :2] - 0.5 * WHEELBASE_M * np.stack([np.cos(pose[..., 2]), np.sin(pose[..., 2])], -1)


def fit(drives: dict) -> MotionModel:
    """The motion model of drives (:func:`training_drives`' arrays): see the module docstring."""
    pose, v, command = drives["pose"], drives["speed_mps"], drives["command"]
    accel = np.diff(v, axis=1) / DT_S  # [W, T-1]: step t's acceleration
    rear = _rear_axle(pose)
    ds = np.linalg.norm(np.diff(rear, axis=1), axis=-1)
    dyaw = wrap_angle(np.diff(pose[..., 2], axis=1))
    v_mid = 0.5 * (v[:, 1:] + v[:, :-1])
    moving = v_mid > MIN_SPEED_MPS
    best = None
    for lag_s in LAG_GRID_S:
        share = 1.0 - np.exp(-DT_S / lag_s) if lag_s > 0 else 1.0
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
    return _with_process_noise(model, drives, rear, ds, dyaw)


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


def calibrate(cfg: Config, **drive_kwargs) -> MotionModel:
    """The motion model of ``cfg``'s world, fitted on :func:`training_drives`."""
    return fit(training_drives(cfg, **drive_kwargs))
