"""Trains and evaluates the modular baselines, each in ``WORKDIR/<baseline>/``.

    python experiments/baselines.py --config=demo --workdir=runs/baselines [--baseline=detector,tracker]

``--baseline``: a comma list of detector, tracker, pose, dead_reckoning (default: all). The detector and
the pose regressor train like the main model (``config.json``, ``metrics.jsonl``, ``checkpoints/``;
resumed if stopped, skipped if finished) on the same ``--config`` and overrides; the tracker evaluates
the detector's run (trained first if needed); dead reckoning trains nothing. Each evaluation goes to
``WORKDIR/<baseline>/eval/`` (``eval_town<seed>/`` with ``--eval.town_seed`` a held-out town): report.md,
metrics.json, pr_curves.png, examples.png, drive.mp4. A bad flag prints one line naming it and exits
with status 1 before anything is compiled.
"""
import os
import sys

from absl import app, flags

from e2e_percep_jax import allocator, xla_cpu
from e2e_percep_jax import baselines, report
from e2e_percep_jax import config as config_lib
from e2e_percep_jax import train as train_lib

config_lib.define_flags()
flags.DEFINE_string("workdir", None, "directory of the baselines' run directories")
flags.DEFINE_list("baseline", list(baselines.BASELINES), f"comma list of {', '.join(baselines.BASELINES)}")
flags.DEFINE_integer("video_frames", 300, "frames of the first evaluation drive in drive.mp4 (0: no video)")
flags.DEFINE_float("odometry_speed_std_mps", 0.1, "dead reckoning: white noise std of each speed sample")
flags.DEFINE_float("odometry_yaw_rate_std_rps", 0.01, "dead reckoning: white noise std of each yaw-rate sample")
FLAGS = flags.FLAGS


def main(argv):
    allocator.keep_freed_buffers()
    xla_cpu.prefer_eigen_convolutions()
    try:
        config_lib.check_launch(argv)
        for name in ("video_frames", "odometry_speed_std_mps", "odometry_yaw_rate_std_rps"):
            if FLAGS[name].value < 0:
                raise ValueError(f"--{name}={FLAGS[name].value}: must be >= 0")
        cfg = config_lib.from_flags()
        baselines.check(FLAGS.baseline, cfg, FLAGS.workdir)
    except ValueError as e:
        sys.exit(f"error: {e}")
    log = lambda s: print(s, flush=True)
    with train_lib.exit_on_stop():
        for name in FLAGS.baseline:
            m = baselines.run(name, cfg, FLAGS.workdir, video_frames=FLAGS.video_frames,
                              speed_noise_std_mps=FLAGS.odometry_speed_std_mps,
                              yaw_rate_noise_std_rps=FLAGS.odometry_yaw_rate_std_rps, log=log)
            log(f"{name} ({m['label']}): {report.eval_dir(os.path.join(FLAGS.workdir, name), cfg)}/report.md")


if __name__ == "__main__":
    app.run(main, flags_parser=config_lib.parse_flags)
