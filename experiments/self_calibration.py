"""How fast the lidar odometry learns each drive's steering offset: frames until its estimate comes within
20 % of the drive's true value, which the world draws and no perceiver sees.

    python experiments/self_calibration.py --workdir=runs/cpu --town_seed=7 [--world.ego_steer_offset_deg=0.5]

Drives ``--drives`` worlds of town ``--town_seed`` (reset from ``--seed``, after the config's warm-up) for
``--frames`` frames and follows each from its true first pose with the run's motion model and the lidar's
scans (``e2e_percep_jax.ego_motion.follow``; the scan matcher's noise is fitted into ``motion_model.json`` the
first time). The estimate is the drive's curvature bias (1/m, beyond the motion model's mean); the truth is
the plant's: the curvature its steering offset gives, tan(offset) / (wheelbase + understeer x v^2) at the
drive's distance-weighted mean v^2, less the model's mean (steer_bias / wheelbase). The distance scale is not
estimated: the scans do not measure it. Prints, as JSON, the share of drives within 20 % at each of
``--at_frames``, each drive's first frame from which it stays within 20 %, and the errors in degrees of
steering offset, each drive's true offset and estimates (as the road-wheel angle in degrees that the
curvature bias amounts to). A ``--world.*`` flag changes the car driven (the model stays the run's).
"""

import json

import jax
import numpy as np
from absl import app, flags

from e2e_percep_jax import calibration, ego_motion, launch
from e2e_percep_jax import config as config_lib
from e2e_percep_jax.sim import motion, world
from e2e_percep_jax.sim import town as town_lib

flags.DEFINE_string("workdir", None, "a training run (its config.json and motion_model.json)")
flags.DEFINE_integer("town_seed", 7, "the town driven")
flags.DEFINE_integer("seed", 1000, "the worlds' reset key")
flags.DEFINE_integer("drives", 16, "drives (worlds)")
flags.DEFINE_integer("frames", 600, "frames driven")
flags.DEFINE_list("at_frames", ["100", "300", "600"], "frames at which the share within 20 % is reported")
FLAGS = flags.FLAGS
WITHIN = 0.2  # the relative error asked of the estimate


def main(argv):
    cfg = launch.run_config(argv, FLAGS.workdir)
    at_frames = [int(f) for f in FLAGS.at_frames]
    if FLAGS.drives < 1 or FLAGS.frames < 1 or not all(0 < f <= FLAGS.frames for f in at_frames):
        raise app.UsageError("--drives and --frames must be >= 1, and every --at_frames in [1, --frames]")
    model = calibration.ensure_scans(cfg, FLAGS.workdir)
    town = town_lib.build_town(FLAGS.town_seed)
    key = jax.random.PRNGKey(FLAGS.seed)
    pose, speed, command, scans = calibration.drives(
        key, town, cfg.world, cfg.data.warmup_steps, FLAGS.drives, FLAGS.frames, scans=True
    )
    # the plants calibration.drives' worlds were reset with (its keys, its reset)
    plant = jax.vmap(lambda k: world.reset(k, town, cfg.world).ego_plant)(jax.random.split(key, FLAGS.drives))
    start, prev_action = calibration.start_and_commands(pose, speed, command)
    _, correction = jax.jit(ego_motion.follow, static_argnums=0)(model, start, prev_action, scans)
    estimate = np.asarray(correction[..., 0], np.float64)  # [W, T] curvature bias (1/m)
    v = np.asarray(speed, np.float64)
    v2 = np.sum(v**3, 1) / np.maximum(np.sum(v, 1), 1e-9)  # v^2 weighted by the distance driven
    effective_wheelbase = motion.WHEELBASE_M + np.asarray(plant.understeer_rad_s2pm, np.float64) * v2
    offset = np.asarray(plant.steer_offset_rad, np.float64)
    truth = np.tan(offset) / effective_wheelbase - model.steer_bias / motion.WHEELBASE_M
    within = np.abs(estimate - truth[:, None]) <= WITHIN * np.abs(truth[:, None])
    # each drive's first frame from which the estimate stays within 20 % to the end (None: not at the end)
    outside = [np.nonzero(~w)[0] for w in within]
    settled = [None if not w[-1] else int(o[-1]) + 1 if o.size else 0 for w, o in zip(within, outside)]
    to_deg = lambda bias: np.degrees(np.arctan(bias * motion.WHEELBASE_M))
    result = {
        "town_seed": FLAGS.town_seed,
        "drives": FLAGS.drives,
        "frames": FLAGS.frames,
        "ego_steer_offset_deg": cfg.world.ego_steer_offset_deg,
        "share_within_20pct": {str(f): float(within[:, f - 1].mean()) for f in at_frames},
        "settled_frame": settled,
        "true_offset_deg": [round(float(v), 4) for v in to_deg(truth)],
        "estimate_deg": {str(f): [round(float(v), 4) for v in to_deg(estimate[:, f - 1])] for f in at_frames},
        "error_deg_abs_median": {
            str(f): float(np.median(np.abs(to_deg(estimate[:, f - 1]) - to_deg(truth)))) for f in at_frames
        },
        "prior_std_deg": float(to_deg(model.yaw_bias_std_1pm)),
    }
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    flags.mark_flag_as_required("workdir")
    app.run(main, flags_parser=config_lib.parse_flags)
