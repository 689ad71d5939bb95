"""A drive's path from the known start: the truth, dead reckoning on the commands and the lidar odometry.

    python experiments/odometry_paths.py --workdir=runs/cpu --town_seed=7 \\
        --out=experiments/figures/odometry_town7.png

Drives one world of town ``--town_seed`` (reset from ``--seed``, after the config's warm-up) for
``--frames`` frames, and follows it from its true first pose by the run's motion model (``motion_model.json``
in ``--workdir``; the scan matcher's noise fitted into it the first time) twice: on the commands alone, and
with the lidar's scans (``e2e_percep_jax.ego_motion``). Writes the town from above with the three paths
(green: true, blue: dead reckoning, red: lidar odometry) and prints each one's error at the end.
"""

import cv2
import jax
import numpy as np
from absl import app, flags

from e2e_percep_jax import calibration, ego_motion, launch, pictures
from e2e_percep_jax import config as config_lib
from e2e_percep_jax.sim import town as town_lib

flags.DEFINE_string("workdir", None, "a training run (its config.json and motion_model.json)")
flags.DEFINE_integer("town_seed", 7, "the town driven")
flags.DEFINE_integer("seed", 1000, "the world's reset key")
flags.DEFINE_integer("frames", 1875, "frames driven")
flags.DEFINE_string("out", "experiments/figures/odometry_town7.png", "the picture written")
FLAGS = flags.FLAGS

DEAD_RECKONING_RGB = (70, 120, 255)


def main(argv):
    cfg = launch.run_config(argv, FLAGS.workdir)
    model = calibration.ensure_scans(cfg, FLAGS.workdir)
    town = town_lib.build_town(FLAGS.town_seed)
    pose, speed, command, scans = calibration.drives(
        jax.random.PRNGKey(FLAGS.seed), town, cfg.world, cfg.data.warmup_steps, 1, FLAGS.frames, scans=True
    )
    start, prev_action = calibration.start_and_commands(pose, speed, command)
    pose = pose[0]
    paths = [(np.asarray(pose[:, :2]), pictures.VISIBLE_RGB)]
    for name, scans, colour in (
        ("dead reckoning", None, DEAD_RECKONING_RGB),
        ("lidar odometry", scans, pictures.ESTIMATE_RGB),
    ):
        estimate = np.asarray(jax.jit(ego_motion.follow, static_argnums=0)(model, start, prev_action, scans)[0][0])
        paths.append((estimate[:, :2], colour))
        error = np.linalg.norm(estimate[:, :2] - np.asarray(pose[:, :2]), axis=-1)
        print(f"{name}: {error.mean():.1f} m mean, {error[-1]:.1f} m at the end")
    travelled = np.sum(np.linalg.norm(np.diff(np.asarray(pose[:, :2]), axis=0), axis=-1))
    print(f"driven: {travelled:.0f} m")
    image = pictures.paths_panel(pictures.TopDown(town, px_per_m=1.5), paths)
    image = pictures.title(image, f"town {FLAGS.town_seed}: true (green), dead reckoning (blue), lidar odometry (red)")
    cv2.imwrite(FLAGS.out, cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    print(f"wrote {FLAGS.out}")


if __name__ == "__main__":
    flags.mark_flag_as_required("workdir")
    app.run(main, flags_parser=config_lib.parse_flags)
