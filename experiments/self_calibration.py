"""How fast the lidar odometry learns each drive's steering offset and distance scale: frames until each
estimate comes within 20 % of the drive's true value, which the world draws and no perceiver sees.

    python experiments/self_calibration.py --workdir=runs/cpu --town_seed=7 [--world.ego_steer_offset_deg=0.5]
    python experiments/self_calibration.py --workdir=runs/cpu --town_seed=8 --pose_drives --at_frames=100,300,1875

Drives ``--drives`` worlds of town ``--town_seed`` (reset from ``--seed``, after the config's warm-up) for
``--frames`` frames (or, with ``--pose_drives``, the evaluation's pose drives of that town) and follows
each from its true first pose with the run's motion model and the lidar's scans
(``e2e_percep_jax.ego_motion.follow``; the scan matcher's noises are fitted into ``motion_model.json``
the first time). Two estimates, each against the plant's truth beyond the motion model's mean:

- the steering offset, as the drive's curvature bias (1/m): the truth is the curvature the plant's offset
  gives, tan(offset) / (wheelbase + understeer x v^2) at the drive's distance-weighted mean v^2, less the
  model's mean (steer_bias / wheelbase); reported as road-wheel degrees;
- the distance scale, as the drive's acceleration gain error (a share): the truth is the plant's distance
  scale times the commands' full scale over the model's acceleration per pedal, less 1. The plant draws the
  scale within a few per cent of 1, so an estimate of 1 is within 20 % of the scale itself from the first
  frame (``scale_within_20pct``, which says nothing); the figure that does is the estimate of its deviation
  from 1 within 20 % of the true deviation (``share_within_20pct``).

Beside them, the odometry's drift per 100 m and mean location error, and the belief's calibration: the
share of frames (after the first metre) whose true location, heading and both lie inside the 95 % regions
of the belief's covariance (``ego_motion.belief_covariance``: the odometry's, its location's variances
times the fitted factor), each with its 95 % bootstrap interval over whole drives.

Prints, as JSON, per estimate: the share of drives within 20 % at each of ``--at_frames``, each drive's first
frame from which it stays within 20 %, the truths and estimates, and the median absolute error. A
``--world.*`` flag changes the car driven (the model stays the run's).
"""

import json

import jax
import numpy as np
from absl import app, flags

from e2e_percep_jax import calibration, ego_motion, evaluate, launch, metrics
from e2e_percep_jax import config as config_lib
from e2e_percep_jax.sim import motion, world
from e2e_percep_jax.sim import town as town_lib

flags.DEFINE_string("workdir", None, "a training run (its config.json and motion_model.json)")
flags.DEFINE_integer("town_seed", 7, "the town driven")
flags.DEFINE_integer("seed", 1000, "the worlds' reset key")
flags.DEFINE_integer("drives", 16, "drives (worlds)")
flags.DEFINE_integer("frames", 600, "frames driven")
flags.DEFINE_list("at_frames", ["100", "300", "600"], "frames at which the share within 20 % is reported")
flags.DEFINE_bool(
    "pose_drives",
    False,
    "drive the evaluation's pose drives (--eval.seed, --eval.num_worlds, --eval.num_frames) instead",
)
FLAGS = flags.FLAGS
WITHIN = 0.2  # the relative error asked of the estimate


def _report(estimate, truth, at_frames):
    """Of ``estimate`` [W, T] against ``truth`` [W]: the share of drives within 20 % of the truth at each
    frame of ``at_frames``, the first frame from which each stays within 20 % (None: not at the end), the
    truths and estimates, and the median absolute error."""
    within = np.abs(estimate - truth[:, None]) <= WITHIN * np.abs(truth[:, None])
    outside = [np.nonzero(~w)[0] for w in within]
    return {
        "share_within_20pct": {str(f): float(within[:, f - 1].mean()) for f in at_frames},
        "settled_frame": [None if not w[-1] else int(o[-1]) + 1 if o.size else 0 for w, o in zip(within, outside)],
        "truth": [round(float(v), 4) for v in truth],
        "estimate": {str(f): [round(float(v), 4) for v in estimate[:, f - 1]] for f in at_frames},
        "error_abs_median": {str(f): float(np.median(np.abs(estimate[:, f - 1] - truth))) for f in at_frames},
    }


def _coverage(squared_distance, chi2_95: float) -> dict:
    """The share of frames whose squared Mahalanobis distance [W, T] (NaN: left out) is inside the 95 %
    region (at most ``chi2_95``), and its 95 % bootstrap interval over whole drives."""
    inside = np.sum(squared_distance <= chi2_95, 1).astype(np.float64)  # [W] (NaN compares False)
    counted = np.sum(~np.isnan(squared_distance), 1).astype(np.float64)
    low, high = metrics.bootstrap_interval(lambda w: (w @ inside) / (w @ counted), len(inside))
    return {"share": float(inside.sum() / counted.sum()), "interval95": [float(low), float(high)]}


def main(argv):
    cfg = launch.run_config(argv, FLAGS.workdir)
    at_frames = [int(f) for f in FLAGS.at_frames]
    if FLAGS.pose_drives:  # the keys evaluate.start_keys splits
        key = evaluate.reset_root(cfg)
        num_drives, num_frames = cfg.eval.num_worlds, cfg.eval.num_frames // cfg.eval.num_worlds
    else:
        key, num_drives, num_frames = jax.random.PRNGKey(FLAGS.seed), FLAGS.drives, FLAGS.frames
    if num_drives < 1 or num_frames < 1 or not all(0 < f <= num_frames for f in at_frames):
        raise app.UsageError("--drives and --frames must be >= 1, and every --at_frames in [1, --frames]")
    model = calibration.ensure_scans(cfg, FLAGS.workdir)
    town = town_lib.build_town(FLAGS.town_seed)
    pose, speed, command, scans = calibration.drives(
        key, town, cfg.world, cfg.data.warmup_steps, num_drives, num_frames, scans=True
    )
    # the plants calibration.drives' worlds were reset with (its keys, its reset)
    plant = jax.vmap(lambda k: world.reset(k, town, cfg.world).ego_plant)(jax.random.split(key, num_drives))
    start, prev_action = calibration.start_and_commands(pose, speed, command)
    followed, estimates, covariance = jax.jit(ego_motion.follow, static_argnums=0)(model, start, prev_action, scans)
    location, heading, joint = calibration.spread_errors(
        pose, followed, ego_motion.belief_covariance(np.asarray(covariance, np.float64), model)
    )
    estimates = np.asarray(estimates, np.float64)  # [W, T, 3]: curvature bias (1/m), yaw gain, accel gain
    v = np.asarray(speed, np.float64)
    v2 = np.sum(v**3, 1) / np.maximum(np.sum(v, 1), 1e-9)  # v^2 weighted by the distance driven
    effective_wheelbase = motion.WHEELBASE_M + np.asarray(plant.understeer_rad_s2pm, np.float64) * v2
    offset = np.asarray(plant.steer_offset_rad, np.float64)
    bias_truth = np.tan(offset) / effective_wheelbase - model.steer_bias / motion.WHEELBASE_M
    scale = np.asarray(plant.distance_scale, np.float64)
    gain_truth = scale * motion.EGO_ACCEL_LIMIT_MPS2 / model.accel_per_pedal_mps2 - 1.0
    to_deg = lambda bias: np.degrees(np.arctan(bias * motion.WHEELBASE_M))
    result = {
        "town_seed": FLAGS.town_seed,
        "drives": num_drives,
        "frames": num_frames,
        "ego_steer_offset_deg": cfg.world.ego_steer_offset_deg,
        "ego_distance_scale_std": cfg.world.ego_distance_scale_std,
        "steering_offset_deg": _report(to_deg(estimates[..., 0]), to_deg(bias_truth), at_frames),
        "acceleration_gain_error": _report(estimates[..., 2], gain_truth, at_frames),
        "scale_within_20pct": {
            str(f): float(np.mean(np.abs(estimates[:, f - 1, 2] - gain_truth) <= WITHIN * (1.0 + gain_truth)))
            for f in at_frames
        },
        # the belief's calibration: moved frames whose truth lies inside the odometry's 95 % regions, each with
        # its 95 % bootstrap interval over whole drives
        "truth_in_95pct_region": {
            name: _coverage(squared, calibration.CHI2_95[dims])
            for name, squared, dims in (
                ("location", location, 2),
                ("heading", heading, 1),
                ("location_heading", joint, 3),
            )
        },
        # the odometry's own figures, as the evaluation computes them
        "drift_per_100m": metrics.drive_pose_summary(np.asarray(pose)[..., :2], np.asarray(followed)[..., :2])[
            "drift_per_100m"
        ],
        "location_m_mean": float(
            np.mean(np.linalg.norm(np.asarray(followed)[..., :2] - np.asarray(pose)[..., :2], axis=-1))
        ),
        "prior_std": {
            "steering_offset_deg": float(to_deg(model.yaw_bias_std_1pm)),
            "acceleration_gain_error": model.speed_gain_std,
        },
    }
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    flags.mark_flag_as_required("workdir")
    app.run(main, flags_parser=config_lib.parse_flags)
