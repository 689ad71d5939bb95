"""Wheel odometry: the ego pose integrated from measured speeds and yaw rates, from a known start pose.

Per step k the rear axle drives ``ds = (v_k + v_{k+1}) / 2 * dt`` (v_0 from the start pose, v_{k+1} the speed
measured at frame k+1) while the yaw changes by ``yaw_rate_k * dt``: the motion model's bicycle step
(:func:`e2e_percep_jax.sim.motion.centre_move`, the world's own kinematic bicycle), so with exact measurements
(:func:`odometry_from_poses`) :func:`dead_reckon` reproduces the world's path up to float rounding.
:func:`noisy_odometry` adds white Gaussian noise from an explicit ``np.random.Generator``;
:class:`DeadReckoner` is the streaming form, one sample per frame.

Everything is float64 NumPy on the host: one small step per frame, where JAX dispatch would dominate.
"""

import numpy as np

from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim.motion import DT_S, centre_move


def odometry_from_poses(poses, dt_s=DT_S):
    """Exact odometry of a pose sequence ``[T+1, 5]``: (speed_mps ``[T]``, yaw_rate_rps ``[T]``).

    speed_mps[k] is the speed at frame k+1 (a wheel-speed sample); yaw_rate_rps[k] the mean yaw rate over the
    step k -> k+1 (a gyro integrated over the step), ``wrap(psi[k+1] - psi[k]) / dt``.
    """
    poses = np.asarray(poses, dtype=np.float64)
    return poses[1:, 4].copy(), geo.wrap_angle(np.diff(geo.pose_yaw(poses))) / dt_s


def noisy_odometry(poses, speed_noise_std_mps, yaw_rate_noise_std_rps, rng: np.random.Generator, dt_s=DT_S):
    """:func:`odometry_from_poses` plus independent zero-mean Gaussian noise of the given stds per sample
    (unclipped: a noisy speed may be negative, so the noise stays unbiased at standstill)."""
    speed, yaw_rate = odometry_from_poses(poses, dt_s)
    return (
        speed + speed_noise_std_mps * rng.standard_normal(speed.shape),
        yaw_rate + yaw_rate_noise_std_rps * rng.standard_normal(yaw_rate.shape),
    )


def dead_reckon(start_pose, speed_mps, yaw_rate_rps, dt_s=DT_S):
    """Integrates the ego pose from odometry (module docstring), vectorised with cumulative sums.

    Args:
      start_pose: ``[5] = (x_m, y_m, cos psi, sin psi, speed_mps)``, the true pose at frame 0.
      speed_mps: ``[T]`` measured speeds at frames 1..T. yaw_rate_rps: ``[T]`` measured mean yaw rates of
        steps 0->1 .. T-1->T.
    Returns:
      poses float64 ``[T+1, 5]`` (frame 0 is the start pose), speed = the measured one.
    """
    start_pose = np.asarray(start_pose, dtype=np.float64)
    speed_mps = np.asarray(speed_mps, dtype=np.float64)
    yaw_rate_rps = np.asarray(yaw_rate_rps, dtype=np.float64)
    if speed_mps.shape != yaw_rate_rps.shape or speed_mps.ndim != 1:
        raise ValueError("speed_mps and yaw_rate_rps must both be [T]")
    speeds_mps = np.concatenate([start_pose[4:5], speed_mps])  # [T+1]
    ds_m = 0.5 * (speeds_mps[:-1] + speeds_mps[1:]) * dt_s  # [T]
    dyaw_rad = yaw_rate_rps * dt_s  # [T]
    yaw_rad = geo.pose_yaw(start_pose) + np.concatenate([[0.0], np.cumsum(dyaw_rad)])  # [T+1], unwrapped
    moves_m = centre_move(ds_m, dyaw_rad, yaw_rad[:-1, None])[:, 0]  # [T, 2]: one heading per step
    centre_xy = start_pose[:2] + np.concatenate([np.zeros((1, 2)), np.cumsum(moves_m, axis=0)])  # [T+1, 2]
    return np.column_stack([centre_xy, np.cos(yaw_rad), np.sin(yaw_rad), speeds_mps])


class DeadReckoner:
    """Streaming :func:`dead_reckon` for online evaluation: one odometry sample per frame, O(1) memory.

    ``DeadReckoner(start_pose).step(speed_mps, yaw_rate_rps)`` returns the pose ``[5]`` of the next frame;
    ``pose`` is the latest one.
    """

    def __init__(self, start_pose, dt_s=DT_S):
        self.pose = np.array(start_pose, dtype=np.float64)  # a copy: the caller may reuse its array
        self.dt_s = dt_s

    def step(self, speed_mps, yaw_rate_rps):
        self.pose = dead_reckon(self.pose, [speed_mps], [yaw_rate_rps], self.dt_s)[1]
        return self.pose
