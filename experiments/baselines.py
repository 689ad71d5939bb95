"""Trains and evaluates the modular baselines, each in ``WORKDIR/<baseline>/``.

    python experiments/baselines.py --config=demo --workdir=runs/baselines [--baseline=detector,tracker]

``--baseline``: a comma list of detector, tracker, pose, dead_reckoning, lidar_odometry, wheel_odometry
(default: all). The detector and the pose regressor train like the main model (``config.json``, ``metrics.jsonl``,
``checkpoints/``; resumed if stopped, skipped if finished) on the same ``--config`` and overrides; the
tracker evaluates the detector's run (trained first if needed); the odometry baselines train nothing
(dead reckoning fits the motion model once) and are evaluated under the known-start protocol. Each evaluation goes to
``WORKDIR/<baseline>/eval/`` (``eval_town<seed>/`` with ``--eval.town_seed`` a held-out town): report.md,
metrics.json, pr_curves.png, examples.png, drive.mp4. A bad flag prints one line naming it and exits
with status 1 before anything is compiled.
"""

import os
import sys

from absl import app, flags

from e2e_percep_jax import config as config_lib
from e2e_percep_jax import launch

config_lib.define_flags()
flags.DEFINE_string("workdir", None, "directory of the baselines' run directories")
flags.DEFINE_list("baseline", list(config_lib.BASELINES), f"comma list of {', '.join(config_lib.BASELINES)}")
flags.DEFINE_integer("video_frames", 300, "frames of the first evaluation drive in drive.mp4 (0: no video)")
FLAGS = flags.FLAGS


def main(argv):
    try:
        launch.prepare(argv)
        if FLAGS.video_frames < 0:
            raise ValueError(f"--video_frames={FLAGS.video_frames}: must be >= 0")
        cfg = config_lib.from_flags()
        # Imported once the flags are valid: a bad flag exits in a fraction of a second, not after ~3 s.
        from e2e_percep_jax import baselines, report
        from e2e_percep_jax import train as train_lib

        cfg = baselines.without_place_stream(cfg)
        baselines.check(FLAGS.baseline, cfg, FLAGS.workdir)
    except ValueError as e:
        sys.exit(f"error: {e}")
    log = lambda s: print(s, flush=True)
    with train_lib.exit_on_stop():
        for name in FLAGS.baseline:
            m = baselines.run(name, cfg, FLAGS.workdir, video_frames=FLAGS.video_frames, log=log)
            out_dir = report.eval_dir(os.path.join(FLAGS.workdir, name), baselines.eval_config(name, cfg))
            log(f"{name} ({m['label']}): {out_dir}/report.md")


if __name__ == "__main__":
    app.run(main, flags_parser=config_lib.parse_flags)
