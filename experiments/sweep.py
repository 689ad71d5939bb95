"""Seed x variant sweeps: every (seed, variant) trained and evaluated online, optionally with the modular
baselines and held-out towns beside them; then one table per evaluation protocol.

    python experiments/sweep.py --config=cpu --sweep_dir=runs/sweep --seeds=0,1 \
        --variants=full,no_input_recon,no_roadmap_recon [--baselines=detector,tracker,pose,dead_reckoning] \
        [--held_out_towns=7,8] [--training_town_known_start] [--parallel=2]

Each run is ``experiments/main.py`` in its own process and directory ``SWEEP_DIR/<variant>-seed<seed>``
(with ``--train.seed`` and ``--model.variant`` set, and every other config flag given here passed on),
evaluated on the training town (``eval/``) and then on each ``--held_out_towns`` town under the
known-start protocol (``eval_town<seed>_known_start/``: an unseen town has no places to recognise, so
the belief starts at the true pose and shows its odometry; detection is measured there as well).
``--training_town_known_start`` adds the training town from the known start (``eval_known_start/``: the
belief's odometry with its measurements, beside dead reckoning's evaluation of the same name). The
``--baselines`` of each seed are ``experiments/baselines.py`` in ``SWEEP_DIR/baselines-seed<seed>/``, on
the same towns and protocols (the pose regressor only on the training town, whose places it learned). Runs go seed by
seed, so a stopped sweep has whole seeds done. It resumes: finished evaluations are skipped, interrupted
trainings continue from their checkpoint. ``--parallel=N`` runs N processes at once (each sees all cores;
on a 2-core machine 1 is fastest). Writes ``SWEEP_DIR/summary<protocol>.json`` and ``.md`` per protocol
(``summary.md``: the training town; ``summary_town7_known_start.md``, ...): mean ± std over seeds of each
metric per method. With a held-out ``--eval.town_seed`` instead, every run is evaluated there alone. The
motion model is fitted once, into ``SWEEP_DIR/motion_model.json``, and copied into each run that would fit
one (the belief's training runs, dead reckoning): they all drive the same world.
The README's tables come from these runs through ``experiments/tables.py --collect``.
"""

import json
import os
import subprocess
import sys
import time

from absl import app, flags

from e2e_percep_jax import config as config_lib
from e2e_percep_jax.summary import markdown_table

HERE = os.path.dirname(os.path.abspath(__file__))
MAIN, BASELINES = os.path.join(HERE, "main.py"), os.path.join(HERE, "baselines.py")

config_lib.define_flags()
flags.DEFINE_string("sweep_dir", None, "one sub-directory per run, and the summaries, go here")
flags.DEFINE_list("seeds", ["0", "1"], "training seeds (--train.seed of each run)")
flags.DEFINE_list("variants", list(config_lib.VARIANTS), f"model variants, any of {config_lib.VARIANTS}")
flags.DEFINE_list("baselines", [], f"modular baselines per seed, any of {config_lib.BASELINES} (default: none)")
flags.DEFINE_list("held_out_towns", [], "town seeds each run is also evaluated on, from the known start")
flags.DEFINE_bool(
    "training_town_known_start", False, "also evaluate each run on its training town from the known start"
)
flags.DEFINE_integer("parallel", 1, "runs at once, as separate processes")
flags.DEFINE_integer("video_frames", 0, "frames of drive.mp4 per run (0: none)")
FLAGS = flags.FLAGS


def run_name(variant: str, seed: int) -> str:
    return f"{variant}-seed{seed}"


def table_markdown(summary: dict, seeds) -> str:
    methods = list(summary)
    keys = list(dict.fromkeys(k for rows in summary.values() for k in rows))  # a baseline may lack a head
    cell = lambda m, s, n: "n/a" if m is None else f"{m:.3g} ± {s:.2g}"
    rows = [[k] + [cell(*summary[m].get(k, (None, None, 0))) for m in methods] for k in keys]
    title = f"Mean ± std over seeds {', '.join(map(str, seeds))} (population std)."
    return f"{title}\n\n{markdown_table(['metric', *methods], rows)}\n"


def _overrides():
    """The config flags given on this command line, to pass on to every run (seed and variant aside)."""
    passed = [f"--config={FLAGS.config}"]
    for section, name, _ in config_lib.fields():
        flag = FLAGS[f"{section}.{name}"]
        if flag.present and f"{section}.{name}" not in ("train.seed", "model.variant"):
            passed.append(f"--{section}.{name}={config_lib.flag_value(flag.value)}")
    return passed


def _int_list(name: str, values) -> list[int]:
    try:
        numbers = [int(v) for v in values]
    except ValueError:
        raise ValueError(f"--{name}={','.join(values)}: expected comma-separated integers")
    if len(set(numbers)) != len(numbers):
        raise ValueError(f"--{name}={','.join(values)}: give distinct values")
    return numbers


def _check(base: config_lib.Config) -> tuple[list[int], list[int]]:
    """The seeds and held-out towns; raises ValueError naming the flag, before anything runs."""
    seeds, towns = _int_list("seeds", FLAGS.seeds), _int_list("held_out_towns", FLAGS.held_out_towns)
    if not seeds:
        raise ValueError("--seeds=: give at least one seed")
    for v in FLAGS.variants:
        if v not in config_lib.VARIANTS:
            raise ValueError(f"--variants: {v!r} is not one of {config_lib.VARIANTS}")
    for b in FLAGS.baselines:
        if b not in config_lib.BASELINES:
            raise ValueError(f"--baselines: {b!r} is not one of {config_lib.BASELINES}")
    if base.world.town_seed in towns:
        raise ValueError(
            f"--held_out_towns={','.join(FLAGS.held_out_towns)}: town {base.world.town_seed} "
            "is the training town (--world.town_seed)"
        )
    if towns and base.eval.town_seed != base.world.town_seed:
        raise ValueError("--held_out_towns: give held-out towns here or in --eval.town_seed, not both")
    if FLAGS.training_town_known_start and (base.eval.known_start or base.eval.town_seed != base.world.town_seed):
        raise ValueError(
            "--training_town_known_start: the runs' own evaluation is already another protocol "
            "(--eval.known_start or a held-out --eval.town_seed)"
        )
    if FLAGS.parallel < 1:
        raise ValueError(f"--parallel={FLAGS.parallel}: must be >= 1")
    return seeds, towns


def _protocols(cfg: config_lib.Config, towns: list[int], training_town: bool = False) -> list[config_lib.Config]:
    """A run's evaluations: ``cfg``'s own, with ``training_town`` its town from the known start, then each
    held-out town from the known start."""
    known_start = lambda t: config_lib.replace(cfg, eval=dict(town_seed=t, known_start=True))
    return [cfg] + [known_start(cfg.eval.town_seed)] * training_town + [known_start(t) for t in towns]


def _protocol_flags(cfg: config_lib.Config, base: config_lib.Config) -> list[str]:
    if cfg.eval == base.eval:
        return []
    return [f"--eval.town_seed={cfg.eval.town_seed}", f"--eval.known_start={cfg.eval.known_start}"]


def _share_motion_model(base: config_lib.Config, run_dirs) -> None:
    """Fits the motion model of the sweep's world once (``SWEEP_DIR/motion_model.json``), with the scan
    matcher's noises that the belief's evaluation moves it by, and gives each of ``run_dirs`` that has none
    a copy. Every run and baseline drives the same world (only the seed and the variant differ), so each
    would fit this same model itself, at a fit's cost each."""
    from e2e_percep_jax import calibration
    from e2e_percep_jax import train as train_lib
    from e2e_percep_jax.sim import motion as motion_lib

    missing = [d for d in run_dirs if not os.path.exists(os.path.join(d, motion_lib.FILE_NAME))]
    if missing:
        model = train_lib.ensure_motion_model(base, FLAGS.sweep_dir)
        if base.model.histogram_belief:
            model = calibration.ensure_scans(base, FLAGS.sweep_dir, spread=False)
        for d in missing:
            os.makedirs(d, exist_ok=True)
            model.save(d)


def main(argv):
    try:
        config_lib.check_launch(argv, required=("sweep_dir",))
        base = config_lib.from_flags()
        seeds, towns = _check(base)
    except ValueError as e:
        sys.exit(f"error: {e}")
    # Imported once the flags are valid: a bad flag exits in ~0.2 s instead of ~3.5 s (flax, orbax, distrax).
    from e2e_percep_jax import baselines as baselines_lib
    from e2e_percep_jax import protocol as protocol_lib
    from e2e_percep_jax import report
    from e2e_percep_jax.summary import mean_std, summary_metrics

    run_cfg = lambda v, s: config_lib.replace(base, train=dict(seed=s), model=dict(variant=v))
    workdir = lambda name: os.path.join(FLAGS.sweep_dir, name)

    def fits_motion(name):
        """The directories of run ``name`` that fit a motion model: a belief's training run, dead reckoning."""
        if name.startswith("baselines-"):
            return [os.path.join(workdir(name), "dead_reckoning")] if "dead_reckoning" in FLAGS.baselines else []
        return [workdir(name)] if base.model.pose_head == "belief" else []

    # (method, evaluation directory) of everything the sweep evaluates
    evaluations = []
    jobs = []  # (run directory name, the commands still to run there, in order)
    for s in seeds:
        for v in FLAGS.variants:
            todo = []
            for cfg in _protocols(run_cfg(v, s), towns, FLAGS.training_town_known_start):
                out_dir = report.eval_dir(workdir(run_name(v, s)), cfg)
                evaluations.append((v, out_dir))
                if report.finished_evaluation(out_dir, v, base.train.num_steps, cfg) is None:
                    todo.append(
                        [
                            MAIN,
                            f"--workdir={workdir(run_name(v, s))}",
                            f"--train.seed={s}",
                            f"--model.variant={v}",
                            *_protocol_flags(cfg, base),
                        ]
                    )
            jobs.append((run_name(v, s), todo))
        if FLAGS.baselines:
            name = run_name("baselines", s)
            todo = []
            for cfg in _protocols(base, towns):  # dead reckoning's own protocol is the known start already
                chosen = baselines_lib.evaluated_under(FLAGS.baselines, cfg, base)
                for b in chosen:
                    evaluations.append(
                        (b, report.eval_dir(os.path.join(workdir(name), b), baselines_lib.eval_config(b, cfg)))
                    )
                if chosen:  # baselines.py itself skips what is already trained and evaluated
                    todo.append(
                        [
                            BASELINES,
                            f"--workdir={workdir(name)}",
                            f"--train.seed={s}",
                            f"--baseline={','.join(chosen)}",
                            *_protocol_flags(cfg, base),
                        ]
                    )
            jobs.append((name, todo))

    model_runs = [todo for name, todo in jobs if not name.startswith("baselines-")]
    print(f"sweep: {len(model_runs)} runs, {sum(not t for t in model_runs)} already finished", flush=True)
    jobs = [(name, todo) for name, todo in jobs if todo]
    os.makedirs(FLAGS.sweep_dir, exist_ok=True)
    _share_motion_model(base, [d for name, _ in jobs for d in fits_motion(name)])

    def start(name, todo):
        os.makedirs(workdir(name), exist_ok=True)
        log = open(os.path.join(workdir(name), "main.log"), "a")
        # the protocol's own flags go last, so they win over a passed-on --eval flag
        cmd = [sys.executable, todo[0][0], *_overrides(), f"--video_frames={FLAGS.video_frames}", *todo[0][1:]]
        print(f"sweep: started {name}: {' '.join(todo[0][1:])} (log: {log.name})", flush=True)
        return name, todo[1:], subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT), log

    running = []
    while jobs or running:
        while jobs and len(running) < FLAGS.parallel:
            running.append(start(*jobs.pop(0)))
        time.sleep(1.0)
        for item in list(running):
            name, todo, proc, log = item
            if proc.poll() is None:
                continue
            running.remove(item)
            log.close()
            if proc.returncode:
                for _, _, other, _ in running:
                    other.terminate()  # they checkpoint on SIGTERM; a rerun resumes them
                sys.exit(f"error: {name} failed with status {proc.returncode}; see {log.name}")
            if todo:
                running.append(start(name, todo))  # the same run's next evaluation
            else:
                print(f"sweep: finished {name}", flush=True)

    by_protocol = {}  # the protocol's name (the metrics record it) -> method -> [metrics per seed]
    for method, out_dir in evaluations:
        with open(os.path.join(out_dir, "metrics.json")) as f:
            metrics = json.load(f)
        name = protocol_lib.from_metrics(metrics, os.path.basename(out_dir)).name
        by_protocol.setdefault(name, {}).setdefault(method, []).append(metrics)
    for protocol, methods in by_protocol.items():
        summary = {m: mean_std([summary_metrics(x) for x in runs]) for m, runs in methods.items()}
        name = "summary" + protocol[len("eval") :]
        with open(os.path.join(FLAGS.sweep_dir, f"{name}.json"), "w") as f:
            json.dump({"seeds": seeds, "config": json.loads(base.to_json()), "summary": summary}, f, indent=1)
        table = table_markdown(summary, seeds)
        with open(os.path.join(FLAGS.sweep_dir, f"{name}.md"), "w") as f:
            f.write(f"{protocol}\n\n{table}")
        print(f"{name}.md:\n{table}")


if __name__ == "__main__":
    app.run(main, flags_parser=config_lib.parse_flags)
