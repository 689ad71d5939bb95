"""Fits a training run's motion model (``motion_model.json``): the motion that the pose belief's filter and
dead reckoning follow, fitted on training drives of the run's world (``e2e_percep_jax/calibration.py``).

    python experiments/calibrate.py --workdir=runs/demo [--refit]

Training fits it at the start of a run with the belief pose head; this launcher fits it for a run that
has none, or again with ``--refit``, with the scan matcher's noise and the odometry's spread that the lidar
odometry reads (which an evaluation from a known start on a held-out town otherwise fits the first time it
needs them). Prints the fitted model. A bad flag prints one line and exits with status 1.
"""

import dataclasses
import os
import sys

from absl import app, flags

from e2e_percep_jax import calibration, launch
from e2e_percep_jax import config as config_lib
from e2e_percep_jax.sim.motion import FILE_NAME

flags.DEFINE_string("workdir", None, "training run directory (its config.json says the world)")
flags.DEFINE_boolean("refit", False, "fit again even if the run has a motion model")
FLAGS = flags.FLAGS


def main(argv):
    cfg = launch.run_config(argv, FLAGS.workdir)
    path = os.path.join(FLAGS.workdir, FILE_NAME)
    if os.path.exists(path) and not FLAGS.refit:
        sys.exit(f"error: {path} exists; --refit fits it again")
    model = calibration.calibrate(cfg, scans=True)
    print(f"wrote {model.save(FLAGS.workdir)}")
    for name, value in dataclasses.asdict(model).items():
        print(f"  {name} = {value:.6g}")


if __name__ == "__main__":
    app.run(main, flags_parser=config_lib.parse_flags)
