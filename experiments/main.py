"""The main job: train a config, evaluate it online, write the report. Resumes whatever is already done.

    python experiments/main.py --config=demo --workdir=runs/demo

Writes into ``--workdir``: ``config.json``, ``metrics.jsonl``, ``checkpoints/`` (training) and
``eval/`` (``report.md``, ``metrics.json``, ``pr_curves.png``, ``examples.png``, ``drive.mp4``), or
``eval_town<seed>/`` with a held-out ``--eval.town_seed``. Run again, it continues an interrupted
training and skips an evaluation that already matches the final checkpoint and the config. Any
``--<section>.<field>`` flag overrides the preset (see ``config.py``).
"""

import os
import sys

from absl import app, flags

from e2e_percep_jax import checkpoint, launch, report
from e2e_percep_jax import config as config_lib
from e2e_percep_jax import evaluate as eval_lib
from e2e_percep_jax import train as train_lib

config_lib.define_flags()
flags.DEFINE_string("workdir", None, "run directory")
flags.DEFINE_integer("video_frames", 300, "frames of the first evaluation drive in drive.mp4 (0: no video)")
FLAGS = flags.FLAGS


def run(cfg: config_lib.Config, workdir: str, video_frames: int = 300, log=print) -> dict:
    """Trains ``cfg`` in ``workdir`` (resuming) and evaluates its final checkpoint into ``workdir/eval``
    (``eval_town<seed>`` for a held-out ``--eval.town_seed``). Returns the evaluation's metrics (read
    back if that checkpoint was already evaluated under the same config)."""
    if train_lib.check_run(cfg, workdir) != cfg.train.num_steps:
        train_lib.train(cfg, workdir)
    out_dir, step = report.eval_dir(workdir, cfg), cfg.train.num_steps
    done = report.finished_evaluation(out_dir, cfg.model.variant, step, cfg)
    if done is not None:
        log(f"{out_dir} already evaluates step {step} under this config; nothing to do")
        return done
    cfg, params, step = checkpoint.restore_params(workdir, cfg, step)
    return eval_lib.evaluate(
        cfg, params, out_dir, video_frames=video_frames, workdir=os.path.abspath(workdir), checkpoint_step=step, log=log
    )


def main(argv):
    try:
        launch.prepare(argv)
        if FLAGS.video_frames < 0:
            raise ValueError(f"--video_frames={FLAGS.video_frames}: must be >= 0")
        cfg = config_lib.from_flags()
        train_lib.check_run(cfg, FLAGS.workdir)
    except ValueError as e:
        sys.exit(f"error: {e}")
    with train_lib.exit_on_stop():
        run(cfg, FLAGS.workdir, FLAGS.video_frames, log=lambda s: print(s, flush=True))
    print(f"report: {os.path.join(report.eval_dir(FLAGS.workdir, cfg), 'report.md')}")


if __name__ == "__main__":
    app.run(main, flags_parser=config_lib.parse_flags)
