"""The ego's motion as the estimators see it: the world's time step and wheelbase, the bicycle step
(:func:`centre_after`, which the world's plant drives too) and the motion model that the pose filter and
dead reckoning on the commands use, whose parameters are fitted on training drives
(:mod:`e2e_percep_jax.calibration`), never taken from the world's plant (which a car does not know).
Wheel odometry (:mod:`e2e_percep_jax.sim.odometry`) drives the same step with measured speeds and yaw rates.

The model, per step, from the logged commands (pedal, steering command):

- actuators: ``actuator += lag_share * (command - actuator)``, the commands seen through a first-order lag;
- speed: ``v' = max(v + (accel_per_pedal_mps2 * pedal + accel_bias_mps2) * DT_S, 0)``, distance
  ``ds = (v + v') / 2 * DT_S``;
- curvature: ``(steer_gain * tan(steer) + steer_bias + understeer_s2pm2 * tan(steer) * v_mid^2) / WHEELBASE_M``
  (a bicycle with a fitted gain and bias, and slip growing with lateral acceleration);
- process noise: per step, heading variance ``heading_noise_rad2pm * ds`` and position variance
  ``position_noise_m2pm * ds`` per axis, fitted so that the errors of the model over horizons up to
  ``CALIBRATION_HORIZONS`` steps are covered (the per-drive parts of the plant, which no fit on other drives
  can know, included).

Importing this module imports no world or town: ``e2e.load`` reads a run's model from its JSON file.
"""

import dataclasses
import json
import os

import jax.numpy as jnp
import numpy as np

from e2e_percep_jax.sim.geometry import array_module, pose_yaw

DT_S = 0.1  # the world's time step (s): one frame
WHEELBASE_M = 2.7  # the kinematic bicycle model's wheelbase
EGO_ACCEL_LIMIT_MPS2 = 3.0  # the pedal's full scale: a pedal of 1 asks for this acceleration
FILE_NAME = "motion_model.json"  # in a run directory


@dataclasses.dataclass(frozen=True)
class MotionModel:
    """Fitted parameters of the ego's motion (module docstring). The defaults are the exact bicycle with
    no lag and no process noise: the world's plant with all its fields at zero."""

    lag_share: float = 1.0
    accel_per_pedal_mps2: float = EGO_ACCEL_LIMIT_MPS2
    accel_bias_mps2: float = 0.0
    steer_gain: float = 1.0
    steer_bias: float = 0.0  # (WHEELBASE_M x curvature at zero steering)
    understeer_s2pm2: float = 0.0
    heading_noise_rad2pm: float = 0.0
    position_noise_m2pm: float = 0.0
    # The lidar odometry's (e2e_percep_jax.ego_motion): the spread over drives of each drive's curvature bias
    # and yaw gain error, the yaw error per metre left within a drive, and the scan matcher's heading error
    # (times the square root of the scans' returns). A scan noise of 0: not fitted, no scans used.
    # (Models saved when the matcher read the lidar image carry its noise as "scan_yaw_noise_rad", and models
    # saved before the scans measured the distance have no "scan_distance_noise": `load` drops the scans'
    # noises and the spread fitted with them, which `calibration.ensure_scans` then fits anew.)
    yaw_bias_std_1pm: float = 0.0
    yaw_gain_std: float = 0.0
    yaw_noise_rad2pm: float = 0.0
    scan_heading_noise_rad: float = 0.0
    # The same for the speed: the spread over drives of each drive's acceleration gain error (the plant's
    # distance scale), the speed's random walk left within a drive (m/s a step), and the factor that turns a
    # match's Gauss-Newton precision of the forward motion into its variance (0: not fitted, the odometry's
    # distance stays the commands').
    speed_gain_std: float = 0.0
    speed_noise_mps: float = 0.0
    scan_distance_noise: float = 0.0
    # The model's own error across its chord (its chord's angle to the true motion's), which the odometry's
    # error covariance carries. (Models saved before it have none: `load` drops their scans' noises and
    # spread, which `calibration.ensure_scans` fits anew.)
    chord_angle_noise_rad: float = 0.0
    # How far the odometry strays from a known start, against what its filters say: the factors on the
    # heading's variances that the odometry's error covariance carries (ego_motion.error_covariance: they
    # move the position too), then on its location's, that put 95 % of the heading and location errors inside
    # their 95 % regions on drives of towns no table uses (`--eval.spread_town_seeds`). A location scale of
    # 0: not fitted; the odometry's belief is then a point. (Models saved when the spread was a law of the
    # distance driven carry "odometry_location_std_at_100m_m": `load` drops it, and
    # `calibration.ensure_scans` fits the factors.)
    odometry_heading_scale: float = 1.0
    odometry_location_scale: float = 0.0

    def save(self, workdir: str) -> str:
        path = os.path.join(workdir, FILE_NAME)
        with open(path + ".tmp", "w") as f:
            json.dump(dataclasses.asdict(self), f, indent=2)
        os.replace(path + ".tmp", path)  # a kill mid-write leaves the old file or none, never half of one
        return path

    @classmethod
    def load(cls, workdir: str) -> "MotionModel":
        """The model saved in run ``workdir``; ValueError naming the file if it is missing or unreadable."""
        path = os.path.join(workdir, FILE_NAME)
        if not os.path.exists(path):
            raise ValueError(f"{path}: missing; fit it with `python experiments/calibrate.py --workdir={workdir}`")
        try:
            with open(path) as f:
                fields = json.load(f)
            if fields.pop("scan_yaw_noise_rad", None) is not None:
                fields = {k: v for k, v in fields.items() if not k.startswith("odometry_")}
            if "odometry_location_std_at_100m_m" in fields:  # the spread as a law of the distance driven
                fields = {k: v for k, v in fields.items() if not k.startswith("odometry_")}
            if "scan_heading_noise_rad" in fields and "chord_angle_noise_rad" not in fields:
                # fitted before the odometry measured its distance, or carried its error covariance: fitted anew
                fields = {k: v for k, v in fields.items() if not k.startswith(("odometry_", "scan_"))}
            return cls(**fields)
        except (ValueError, TypeError, AttributeError) as e:
            raise ValueError(f"{path}: not a motion model ({type(e).__name__}: {e})") from None


def lag_share(lag_s: float) -> float:
    """The share of the gap to its command that a first-order lag of time constant ``lag_s`` closes in a
    step (1: no lag)."""
    return float(1.0 - np.exp(-DT_S / lag_s)) if lag_s > 0 else 1.0


def lag_step(share, actuator, command):
    """Actuators [...] one step of a first-order lag closing ``share`` of the gap towards ``command``; at
    share 1, the command bit for bit (``where``, not the formula, which rounds). The world's plant and the
    motion model take this one step; NumPy in, NumPy out."""
    xp = array_module(share, actuator, command)
    return xp.where(share == 1.0, command, actuator + share * (command - actuator))


def speed_step(speed_mps, accel_mps2):
    """(speed after a step of acceleration ``accel_mps2`` [...], never below 0; the distance driven [...] m
    at the step's mean speed). The world's plant and the motion model take this one step (in JAX, float32
    unless x64 is on, whatever the inputs: the calibration's fit reads it so)."""
    v_new = jnp.maximum(speed_mps + accel_mps2 * DT_S, 0.0)
    return v_new, 0.5 * (speed_mps + v_new) * DT_S


def actuate(model: MotionModel, actuator, command):
    """The actuators' state [..., 2] (pedal, steering rad) after one step towards ``command`` [..., 2]."""
    return lag_step(model.lag_share, actuator, command)


def acceleration(model: MotionModel, actuator):
    """The acceleration [...] (m/s^2) the actuators [..., 2] ask of the car."""
    return model.accel_per_pedal_mps2 * actuator[..., 0] + model.accel_bias_mps2


def speed_and_distance(model: MotionModel, actuator, speed_mps, accel_gain=1.0):
    """(speed after the step [...], distance driven [...] m) from the actuators [..., 2] and the speed before;
    the acceleration times ``accel_gain`` [...] (a drive's estimated distance scale)."""
    return speed_step(speed_mps, accel_gain * acceleration(model, actuator))


def curvature(model: MotionModel, steer_rad, mid_speed_mps):
    """Curvature (1/m) of the path under road-wheel command ``steer_rad`` at speed ``mid_speed_mps``."""
    tan = jnp.tan(steer_rad)
    return (model.steer_gain * tan + model.steer_bias + model.understeer_s2pm2 * tan * mid_speed_mps**2) / WHEELBASE_M


def centre_after(xy_m, yaw_rad, ds_m, yaw_new_rad):
    """The kinematic bicycle's step, written once (the world's plant, the pose filter and dead reckoning move
    the ego through it): the car's centre [..., 2] after its rear axle, half a wheelbase behind the centre
    ``xy_m`` [..., 2], drives ``ds_m`` [...] along the mid-step heading while the heading goes from
    ``yaw_rad`` to ``yaw_new_rad`` [...]. NumPy inputs give NumPy in their dtype (float64 stays float64),
    JAX inputs give JAX (``geometry.array_module``)."""
    xp = array_module(xy_m, yaw_rad, ds_m, yaw_new_rad)
    unit = lambda a: xp.stack([xp.cos(a), xp.sin(a)], -1)
    rear_m = xy_m - 0.5 * WHEELBASE_M * unit(yaw_rad)
    mid_rad = 0.5 * (yaw_rad + yaw_new_rad)
    return rear_m + ds_m[..., None] * unit(mid_rad) + 0.5 * WHEELBASE_M * unit(yaw_new_rad)


def centre_move(ds_m, dyaw_rad, yaw_rad):
    """Displacement [..., K, 2] of the car's centre (:func:`centre_after`) for K headings ``yaw_rad``
    [..., K], given the distance ``ds_m`` [...] its rear axle drives and its yaw change ``dyaw_rad`` [...]."""
    return centre_after(0.0, yaw_rad, ds_m[..., None], yaw_rad + dyaw_rad[..., None])


def drive(model: MotionModel, actuator, command, speed_mps, accel_gain=1.0):
    """One step of the motion model without a heading: (actuators after [..., 2], speed after [...], distance
    [...] m, yaw change [...] rad); the acceleration times ``accel_gain`` [...]."""
    actuator = actuate(model, actuator, command)
    v_new, ds = speed_and_distance(model, actuator, speed_mps, accel_gain)
    return actuator, v_new, ds, ds * curvature(model, actuator[..., 1], 0.5 * (speed_mps + v_new))


def step(model: MotionModel, actuator, command, speed_mps, yaw_rad):
    """One step of the motion model for K headings: (actuators after [..., 2], speed after [...], distance
    [...] m, centre displacement [..., K, 2] m, yaw change [...] rad)."""
    actuator, v_new, ds, dyaw = drive(model, actuator, command, speed_mps)
    return actuator, v_new, ds, centre_move(ds, dyaw, yaw_rad), dyaw


def advance_pose(model: MotionModel, actuator, command, pose):
    """Poses [B, 5] (x m, y m, cos, sin, speed m/s) one step on by ``command`` [B, 2] from actuators
    [B, 2]: (actuators after, poses after). An odometry's step (dead reckoning on the commands)."""
    yaw = pose_yaw(pose)
    actuator, v_new, _, move, dyaw = step(model, actuator, command, pose[:, 4], yaw[:, None])
    yaw = yaw + dyaw
    return actuator, jnp.concatenate([pose[:, :2] + move[:, 0], jnp.stack([jnp.cos(yaw), jnp.sin(yaw), v_new], -1)], -1)
