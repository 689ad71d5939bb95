"""Seed x variant sweeps: one training + online evaluation per (seed, variant), then one table.

    python experiments/sweep.py --config=cpu --sweep_dir=runs/sweep --seeds=0,1 \
        --variants=full,no_input_recon,no_roadmap_recon [--parallel=2] [--eval.town_seed=7]

Each run is ``experiments/main.py`` in its own process and directory ``SWEEP_DIR/<variant>-seed<seed>``
(with ``--train.seed`` and ``--model.variant`` set, and every other config flag given here passed on).
A stopped sweep resumes: finished runs are skipped, interrupted ones continue from their checkpoint.
``--parallel=N`` runs N processes at once (each sees all cores; on a 2-core machine 1 is fastest).
Writes ``SWEEP_DIR/summary.json`` and ``summary.md``: mean ± std over seeds of each metric per variant.
With a held-out ``--eval.town_seed`` the trained runs are re-evaluated there (into each run's
``eval_town<seed>/``) and the table goes to ``summary_town<seed>.json`` and ``.md``.
"""
import json
import os
import subprocess
import sys
import time

from absl import app, flags

from e2e_percep_jax import config as config_lib
from e2e_percep_jax import report
from e2e_percep_jax.summary import mean_std, summary_metrics

MAIN = os.path.join(os.path.dirname(os.path.abspath(__file__)), "main.py")

config_lib.define_flags()
flags.DEFINE_string("sweep_dir", None, "one sub-directory per run, and the summary, go here")
flags.DEFINE_list("seeds", ["0", "1"], "training seeds (--train.seed of each run)")
flags.DEFINE_list("variants", list(config_lib.VARIANTS), f"model variants, any of {config_lib.VARIANTS}")
flags.DEFINE_integer("parallel", 1, "runs at once, as separate processes")
flags.DEFINE_integer("video_frames", 0, "frames of drive.mp4 per run (0: none)")
FLAGS = flags.FLAGS


def run_name(variant: str, seed: int) -> str:
    return f"{variant}-seed{seed}"


def table_markdown(summary: dict, seeds) -> str:
    variants = list(summary)
    keys = list(next(iter(summary.values())))
    cell = lambda m, s, n: "n/a" if m is None else f"{m:.3g} ± {s:.2g}"
    lines = [f"Mean ± std over seeds {', '.join(map(str, seeds))} (population std).", "",
             "| metric | " + " | ".join(variants) + " |", "|---" * (len(variants) + 1) + "|"]
    lines += [f"| {k} | " + " | ".join(cell(*summary[v][k]) for v in variants) + " |" for k in keys]
    return "\n".join(lines) + "\n"


def _overrides():
    """The config flags given on this command line, to pass on to every run (seed and variant aside)."""
    passed = [f"--config={FLAGS.config}"]
    for section, name, _ in config_lib.fields():
        flag = FLAGS[f"{section}.{name}"]
        if flag.present and f"{section}.{name}" not in ("train.seed", "model.variant"):
            passed.append(f"--{section}.{name}={config_lib.flag_value(flag.value)}")
    return passed


def main(argv):
    try:
        config_lib.check_launch(argv, required=("sweep_dir",))
        try:
            seeds = [int(s) for s in FLAGS.seeds]
        except ValueError:
            raise ValueError(f"--seeds={','.join(FLAGS.seeds)}: expected comma-separated integers")
        if not seeds or len(set(seeds)) != len(seeds):
            raise ValueError(f"--seeds={','.join(FLAGS.seeds)}: give distinct seeds")
        for v in FLAGS.variants:
            if v not in config_lib.VARIANTS:
                raise ValueError(f"--variants: {v!r} is not one of {config_lib.VARIANTS}")
        if FLAGS.parallel < 1:
            raise ValueError(f"--parallel={FLAGS.parallel}: must be >= 1")
        base = config_lib.from_flags()
    except ValueError as e:
        sys.exit(f"error: {e}")

    runs = [(v, s) for v in FLAGS.variants for s in seeds]
    run_cfg = lambda v, s: config_lib.replace(base, train=dict(seed=s), model=dict(variant=v))
    out_dir = lambda v, s: report.eval_dir(os.path.join(FLAGS.sweep_dir, run_name(v, s)), run_cfg(v, s))
    done = lambda v, s: report.finished_evaluation(out_dir(v, s), v, base.train.num_steps, run_cfg(v, s))

    todo = [(v, s) for v, s in runs if done(v, s) is None]
    print(f"sweep: {len(runs)} runs, {len(runs) - len(todo)} already finished", flush=True)
    os.makedirs(FLAGS.sweep_dir, exist_ok=True)
    running = []
    while todo or running:
        while todo and len(running) < FLAGS.parallel:
            v, s = todo.pop(0)
            workdir = os.path.join(FLAGS.sweep_dir, run_name(v, s))
            os.makedirs(workdir, exist_ok=True)
            cmd = [sys.executable, MAIN, f"--workdir={workdir}", f"--train.seed={s}", f"--model.variant={v}",
                   f"--video_frames={FLAGS.video_frames}", *_overrides()]
            log = open(os.path.join(workdir, "main.log"), "a")
            running.append(((v, s), subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT), log))
            print(f"sweep: started {run_name(v, s)} (log: {log.name})", flush=True)
        time.sleep(1.0)
        for item in list(running):
            (v, s), proc, log = item
            if proc.poll() is None:
                continue
            running.remove(item)
            log.close()
            if proc.returncode:
                for _, other, _ in running:
                    other.terminate()  # they checkpoint on SIGTERM; a rerun resumes them
                sys.exit(f"error: run {run_name(v, s)} failed with status {proc.returncode}; see {log.name}")
            print(f"sweep: finished {run_name(v, s)}", flush=True)

    summary = {v: mean_std([summary_metrics(done(v, s)) for s in seeds]) for v in FLAGS.variants}
    name = "summary" if base.eval.town_seed == base.world.town_seed else f"summary_town{base.eval.town_seed}"
    with open(os.path.join(FLAGS.sweep_dir, f"{name}.json"), "w") as f:
        json.dump({"seeds": seeds, "config": json.loads(base.to_json()), "summary": summary}, f, indent=1)
    table = table_markdown(summary, seeds)
    with open(os.path.join(FLAGS.sweep_dir, f"{name}.md"), "w") as f:
        f.write(table)
    print(table)


if __name__ == "__main__":
    app.run(main, flags_parser=config_lib.parse_flags)
