"""Evaluates a trained run online and writes RUN/<the protocol's name>/ (``eval`` as the run was configured,
``eval_town<seed>`` on a held-out ``--eval.town_seed``, ``_known_start`` under ``--eval.known_start``, a
suffix for every other field changed: ``e2e_percep_jax.protocol``): metrics.json, report.md, pr_curves.png,
examples.png, drive.mp4.

    python experiments/evaluate.py --workdir=runs/demo [--eval.num_frames=2000 --sample --video_frames=300]

The run's config.json is the config; ``--eval.<field>`` flags override its evaluation section
(number of frames, worlds, start-key seed, town, chunk size, the operating score, the detection
candidates, score floor and NMS threshold, the pose protocol: ``--eval.known_start`` starts the pose
belief at each drive's true first pose), and
``--model.pose_filter`` (``none``: the belief head read frame by frame, without the histogram filter).
Other fields are the trained model's and cannot change. A bad flag prints one line and exits with status 1.
"""

import os
import sys

from absl import app, flags

from e2e_percep_jax import config as config_lib
from e2e_percep_jax import launch, protocol

config_lib.define_flags()
flags.DEFINE_string("workdir", None, "run directory holding config.json and checkpoints/")
flags.DEFINE_string(
    "out_dir",
    None,
    "where the report goes (default: WORKDIR/<the protocol's name>: eval, or eval_town<seed> with a "
    "held-out --eval.town_seed, then _known_start, _no_pose_filter and a suffix per other changed field)",
)
flags.DEFINE_integer("step", None, "checkpoint step to evaluate (default: the latest)")
flags.DEFINE_boolean("sample", False, "filter with posterior samples instead of the posterior mean")
flags.DEFINE_integer("video_frames", 300, "frames of world 0 in drive.mp4 (0: no video)")
flags.DEFINE_integer("num_examples", 2, "example frames in examples.png")
FLAGS = flags.FLAGS
# Fields outside --eval.* that change no parameter (the protocol's: the world's plant, the same network in
# another car, and the pose filter)
INFERENCE_FIELDS = tuple(f"{section}.{name}" for section, name in protocol.EVALUATION_FIELDS if section != "eval")


def main(argv):
    try:
        launch.prepare(argv)
        if FLAGS["config"].present:
            raise ValueError("--config: the run's config.json is the config; only --eval.* may change")
        overrides = {}
        for section, name, _ in config_lib.fields():
            flag = f"{section}.{name}"
            if not FLAGS[flag].present:
                continue
            if section != "eval" and flag not in INFERENCE_FIELDS:
                raise ValueError(
                    f"--{flag}: only --eval.*, --model.pose_filter and the plant's --world.ego_* "
                    f"may change at evaluation (the model is trained)"
                )
            overrides.setdefault(section, {})[name] = FLAGS[flag].value
        cfg = config_lib.validate(config_lib.replace(config_lib.run_config(FLAGS.workdir), **overrides))
        if FLAGS.video_frames < 0 or FLAGS.num_examples < 0:
            raise ValueError("--video_frames and --num_examples must be >= 0")
        # Imported once the flags are valid: a bad flag exits in a fraction of a second, not after ~3 s of
        # imports (orbax, flax, distrax, OpenCV).
        from e2e_percep_jax import checkpoint, report
        from e2e_percep_jax import evaluate as eval_lib
        from e2e_percep_jax.sim import world

        world.check_vehicle_count(cfg.world, cfg.eval.town_seed)
        cfg, params, step = checkpoint.restore_params(FLAGS.workdir, cfg, FLAGS.step)
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"error: {e}")
    eval_lib.evaluate(
        cfg,
        params,
        FLAGS.out_dir or report.eval_dir(FLAGS.workdir, cfg),
        sample=FLAGS.sample,
        video_frames=FLAGS.video_frames,
        num_examples=FLAGS.num_examples,
        workdir=os.path.abspath(FLAGS.workdir),
        checkpoint_step=step,
        log=lambda s: print(s, flush=True),
    )


if __name__ == "__main__":
    app.run(main, flags_parser=config_lib.parse_flags)
