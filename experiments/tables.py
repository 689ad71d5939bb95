"""The README's result tables, rendered from the runs' evaluations, never typed.

    # keep the evaluations a table reads: every eval*/metrics.json of the runs, without its PR curves
    python experiments/tables.py --collect=cpu=runs/cpu_s0,runs/cpu_s1 --collect=dead_reckoning=runs/baselines/dead_reckoning
    # write the tables into README.md between its <!-- table:<name>:begin/end --> markers
    python experiments/tables.py --readme=README.md
    # exit 1 if README.md's tables differ from what the kept evaluations render (tests/test_tables.py)
    python experiments/tables.py --readme=README.md --check
    # the learning curves of the kept runs: training loss, place term, location error and AP@0.5
    python experiments/tables.py --figure=experiments/figures/learning_curves.png

The kept evaluations live in ``--results`` (default ``experiments/results/``) as
``<method>/<run>/<evaluation>.json``: a method is a recipe (a row), a run one seed of it, an evaluation one
of the run's ``eval*`` directories, read by the protocol its metrics record (:mod:`e2e_percep_jax.protocol`:
``eval``, the training town's global protocol; ``eval_town7``, a held-out town; ``_known_start``, the belief
starts at the true pose); the held-out towns are those the kept evaluations drove. Each cell is the mean ± std over a
method's runs; each method's row names the command that trained it. Beside them, ``training.jsonl``
keeps every 100th record of the run's ``metrics.jsonl`` for the learning curves' figure.
"""

import dataclasses
import glob
import json
import os
import re
import sys

import cv2
import numpy as np
from absl import app, flags

from e2e_percep_jax import baselines as baselines_lib
from e2e_percep_jax import checkpoint, pictures, pose_belief, protocol, report, train_state
from e2e_percep_jax import config as config_lib
from e2e_percep_jax import metrics as metrics_lib
from e2e_percep_jax.summary import markdown_table, mean_std, summary_metrics

HERE = os.path.dirname(os.path.abspath(__file__))
DROPPED = {"detection": ("pr_curves", "at_threshold"), "": ("examples", "sample")}  # large, no table reads them
EARLIER_FILTER = " †"  # after a method whose pose figures another filter made (_earlier_filter)
EARLIER_FILTER_NOTE = (
    "- † Pose figures from the filter's settings before 2026-11-27 (every frame measured in full, the car "
    "standing or not): [BUILD_NOTES](BUILD_NOTES.md#measurements-while-the-car-stands)."
)
COMMANDS_ONLY = " ‡"  # after a held-out town's drift that the commands alone made (_commands_only)
COMMANDS_ONLY_NOTE = (
    "- ‡ Evaluated before the lidar odometry: on a town the model never saw, the belief followed the commands "
    "alone (the network plays no part there): [BUILD_NOTES](BUILD_NOTES.md#odometry-from-the-lidar-on-towns-never-seen)."
)
TOWN0_COMMANDS = " ¶"  # after a method whose town-0 belief the commands alone moved (_commands_only)
TOWN0_COMMANDS_NOTE = (
    "- ¶ Town 0's belief moved by the commands alone between place measurements, before the lidar odometry "
    "moved it there too: [BUILD_NOTES](BUILD_NOTES.md#odometry-from-the-lidar-on-towns-never-seen)."
)
IMAGE_MATCHER = " §"  # after a held-out town's drift that the odometry made by matching lidar images
IMAGE_MATCHER_NOTE = (
    "- § The lidar odometry matched the bird-eye lidar image (0.5 m pixels, 16-20 m out) before it matched "
    "the lidar's own scan: [BUILD_NOTES](BUILD_NOTES.md#odometry-from-the-lidar-on-towns-never-seen)."
)
WHOLE_CELLS = " ∥"  # after a coverage whose region was whole cells (_whole_cells)
WHOLE_CELLS_NOTE = (
    "- ∥ The region was counted in whole cells before its edge cells were counted in part: it held more than "
    "95 % of the belief, and the truth more often: "
    "[BUILD_NOTES](BUILD_NOTES.md#a-region-that-holds-95--of-the-belief-2026-12-01)."
)
TRAINING_EVERY = 100  # steps between the kept training records (a 9,000-step run: 90 lines)
# BGR, one per method in the learning curves' figure
COLOURS = (
    (200, 120, 30),
    (30, 110, 230),
    (40, 160, 40),
    (160, 40, 160),
    (40, 40, 200),
    (120, 120, 120),
    (0, 170, 200),
    (140, 90, 60),
    (20, 20, 20),
    (200, 200, 0),
    (120, 60, 220),
    (90, 200, 140),
    (60, 60, 140),
    (180, 180, 90),
)

flags.DEFINE_multi_string("collect", [], "METHOD=RUN_DIR[,RUN_DIR...]: keep these runs' evaluations as METHOD")
flags.DEFINE_string("results", os.path.join(HERE, "results"), "directory of the kept evaluations")
flags.DEFINE_string("readme", None, "markdown file whose table markers to fill (default: print the tables)")
flags.DEFINE_boolean("check", False, "with --readme: exit 1 if its tables differ from the rendered ones")
flags.DEFINE_string("figure", None, "also draw the learning curves of the kept runs into this PNG")
FLAGS = flags.FLAGS


# ----------------------------------------------------------------------------- the kept evaluations


def collect(method: str, run_dirs: list[str], results_dir: str) -> list[str]:
    """Copies each run's ``eval*/metrics.json`` (without the large fields) into
    ``results_dir/method/<run name>/<evaluation>.json``; returns the paths written."""
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", method):
        raise ValueError(f"--collect={method}=...: a method name is letters, digits, '_', '.' or '-'")
    written = []
    # a run's name is its path below the runs' common folder ("baselines-seed0-detector" beside
    # "baselines-seed1-detector"), or its folder's name if it is alone
    paths = [os.path.abspath(r) for r in run_dirs]
    common = os.path.commonpath(paths) if len(paths) > 1 else os.path.dirname(paths[0])
    for run, run_path in zip(run_dirs, paths):
        name = os.path.relpath(run_path, common).replace(os.sep, "-")
        evaluations = sorted(glob.glob(os.path.join(run, "eval*", "metrics.json")))
        if not evaluations:
            raise ValueError(f"--collect={method}={run}: no eval*/metrics.json in {run}")
        kept = []
        for path in evaluations:
            with open(path) as f:
                metrics = json.load(f)
            kept.append(metrics)
            for section, keys in DROPPED.items():
                for key in keys:
                    (metrics[section] if section else metrics).pop(key, None)
            out = os.path.join(results_dir, method, name, os.path.basename(os.path.dirname(path)) + ".json")
            os.makedirs(os.path.dirname(out), exist_ok=True)
            with open(out, "w") as f:
                json.dump(metrics, f, indent=1, sort_keys=True)
            written.append(out)
        # up to the last evaluated checkpoint: a run may have trained on since
        last = max(map(_trained_steps, kept))
        record = keep_training_record(run, os.path.join(results_dir, method, name), last)
        written += [record] if record else []
    return written


def keep_training_record(run: str, out_dir: str, last_step: int) -> str | None:
    """Every ``TRAINING_EVERY``-th step of ``run/metrics.jsonl`` (the losses, gradient norm and counters) up
    to ``last_step`` into ``out_dir/training.jsonl``; its path, or None where the run has no record."""
    path = os.path.join(run, "metrics.jsonl")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        records = [r for r in map(json.loads, f) if r["step"] % TRAINING_EVERY == 0 and r["step"] <= last_step]
    by_step = {r["step"]: r for r in records}  # a resumed run logs the steps since its checkpoint again
    out = os.path.join(out_dir, "training.jsonl")
    with open(out, "w") as f:
        f.writelines(json.dumps(by_step[step], sort_keys=True) + "\n" for step in sorted(by_step))
    return out


def load_training(results_dir: str) -> dict:
    """{method: [[training records] per run]}, runs in name order."""
    found = {}
    for path in sorted(glob.glob(os.path.join(results_dir, "*", "*", "training.jsonl"))):
        with open(path) as f:
            found.setdefault(os.path.basename(os.path.dirname(os.path.dirname(path))), []).append(
                [json.loads(line) for line in f]
            )
    return found


def load(results_dir: str) -> dict:
    """{method: {evaluation: [metrics per run]}}, runs in name order, an evaluation named by its protocol
    (``protocol.Protocol.name``); each metrics dict gains ``run``, its run directory's name (a baseline's is
    the baseline's name), and ``protocol`` where it was written before evaluations recorded theirs."""
    found = {}
    for path in sorted(glob.glob(os.path.join(results_dir, "*", "*", "*.json"))):
        run_dir = os.path.dirname(path)
        with open(path) as f:
            metrics = dict(json.load(f), run=os.path.basename(run_dir))
        evaluation = protocol.from_metrics(metrics, os.path.basename(path)[:-5])
        metrics["protocol"] = evaluation.to_dict()
        found.setdefault(os.path.basename(os.path.dirname(run_dir)), {}).setdefault(evaluation.name, []).append(metrics)
    return found


def held_out_towns(found: dict) -> tuple:
    """The towns, other than the training town, that some kept evaluation drove."""
    return tuple(
        sorted(
            {
                m["protocol"]["town_seed"]
                for evaluations in found.values()
                for runs in evaluations.values()
                for m in runs
                if m["protocol"]["held_out"]
            }
        )
    )


def _trained_steps(metrics: dict) -> int:
    """The training steps behind an evaluation: its checkpoint's, or (where not recorded) the run's own."""
    step = metrics.get("checkpoint_step")
    return metrics["config"]["train"]["num_steps"] if step is None else step


def _checkpoint_evaluations(evaluations: dict) -> dict:
    """{step: [metrics per run]} of a method's ``eval_step<N>`` evaluations (its checkpoints')."""
    return {
        int(name[len("eval_step") :]): runs for name, runs in evaluations.items() if re.fullmatch(r"eval_step\d+", name)
    }


def _main_runs(evaluations: dict) -> list[dict]:
    """A method's runs as its ``eval`` (or, lacking one, its first) evaluation has them."""
    return evaluations.get("eval") or next(iter(evaluations.values()))


def _as_trained(m: dict) -> tuple:
    """(the config whose command trains a run's evaluated checkpoint, the step it was stopped at or None). At a
    constant learning rate a checkpoint is a run of that many steps; under a decaying one, so is a checkpoint
    before the decay starts (the rate was constant up to it); a later one short of ``num_steps`` is the run of
    its own ``num_steps`` stopped there (a signal, a lease ended)."""
    cfg, steps = config_lib.Config.from_dict(m["config"]), _trained_steps(m)
    if not cfg.train.lr_decay_share:
        return config_lib.replace(cfg, train=dict(num_steps=steps)), None
    if steps <= train_state.decay_start(cfg):
        return config_lib.replace(cfg, train=dict(num_steps=steps, lr_decay_share=0.0)), None
    return cfg, (steps if steps < cfg.train.num_steps else None)


def command(evaluations: dict) -> str:
    """The training command of a method's runs (``{0,1}`` where the seeds differ; the evaluation's own
    flags left out)."""
    runs = _main_runs(evaluations)
    trained = lambda m: _as_trained(m)[0]

    # left out: the evaluation's flags, and those a run may change on resuming (they leave its weights as they are)
    unsaid = ("--eval.", *(f"--{name}=" for name in checkpoint.RESUMABLE_CHANGES if name != "train.num_steps"))
    lines = {" ".join(f for f in config_lib.as_flags(trained(m)) if not f.startswith(unsaid)) for m in runs}
    seeds = sorted({m["config"]["train"]["seed"] for m in runs})
    if len(seeds) > 1:
        lines = {
            re.sub(r" --train\.seed=\d+", "", line) + f" --train.seed={{{','.join(map(str, seeds))}}}" for line in lines
        }
    if len(lines) != 1:
        raise ValueError(f"a method's runs differ in more than their seed: {sorted(lines)}")
    if runs[0]["label"] in config_lib.VARIANTS:
        return f"python experiments/main.py {lines.pop()}"
    # a baseline's run is named after it ("detector", or "baselines-seed0-detector" collected from a sweep)
    name = next(b for b in config_lib.BASELINES if re.fullmatch(rf"(.*-)?{b}", runs[0]["run"]))
    return f"python experiments/baselines.py --baseline={name} {lines.pop()}"


def stopped_at(evaluations: dict) -> int | None:
    """The step at which a method's runs were stopped inside their learning rate's decay (a signal, a lease
    ended), where :func:`command` trains them further: the runs' step, or None."""
    stops = {_as_trained(m)[1] for m in _main_runs(evaluations)} - {None}
    if len(stops) > 1:
        raise ValueError(f"a method's runs were stopped at different steps: {sorted(stops)}")
    return stops.pop() if stops else None


# ----------------------------------------------------------------------------- cells


def _format(mean, std, n, digits=1) -> str:
    """mean ± std (the std only over more than one run), or "" where no run has the number."""
    if mean is None:
        return ""
    return f"{mean:.{digits}f}" + (f" ± {std:.{digits}f}" if n > 1 else "")


def _bounds(evaluations: list[dict], get, scale: float, digits: int) -> str:
    """ " [low, high]": each run's 95 % interval over drives (``get(metrics)``: (low, high), or None for an
    evaluation made before it had one) times ``scale``, its bounds averaged over the runs; "" unless every run
    has it."""
    bounds = [get(m) for m in evaluations]
    if not bounds or any(b is None or None in b for b in bounds):
        return ""
    low, high = (scale * np.mean([b[i] for b in bounds]) for i in (0, 1))
    return f" [{low:.{digits}f}, {high:.{digits}f}]"


def _cell(evaluations: list[dict] | None, row: str, digits: int = 1, interval: str | None = None) -> str:
    """Mean ± std over the runs of one summary row, or "" where no run has it; with ``interval`` (a key of
    metrics.json's ``pose.interval95``), then the interval over drives (:func:`_bounds`)."""
    if not evaluations:
        return ""
    cell = _format(*mean_std([summary_metrics(m) for m in evaluations]).get(row, (None, None, 0)), digits=digits)
    if not cell or interval is None:
        return cell
    scale = 100.0 if row.endswith("(%)") else 1.0
    return cell + _pose_bounds(evaluations, interval, scale, digits)


def _pose_bounds(evaluations: list[dict], name: str, scale: float, digits: int) -> str:
    """:func:`_bounds` of the pose figure ``name`` (a key of metrics.json's ``pose.interval95``)."""
    return _bounds(evaluations, lambda m: m["pose"].get("interval95", {}).get(name), scale, digits)


def _error_by_frames(metrics: dict, lo: int, hi: int) -> float | None:
    """The mean location error (m) over frames [lo, hi) of each drive, from the evaluation's bins."""
    by_step = metrics["pose"]["location_m_by_step"]
    edges, total, count = by_step["bin_edges"], 0.0, 0
    for a, b, mean, n in zip(edges[:-1], edges[1:], by_step["mean"], by_step["count"]):
        if lo <= a and b <= hi and n:
            total, count = total + mean * n, count + n
    return total / count if count else None


def _frames_cell(evaluations: list[dict] | None, span: str) -> str:
    """Mean ± std over the runs of the location error over one of ``metrics_lib.FRAME_SPANS``, then its interval
    over drives (:func:`_pose_bounds`) where every run has one."""
    if not evaluations:
        return ""
    first, last = metrics_lib.FRAME_SPANS[span]
    errors = [{"error": _error_by_frames(m, first, last or np.inf)} for m in evaluations]
    cell = _format(*mean_std(errors)["error"])
    return cell and cell + _pose_bounds(evaluations, span, 1.0, 1)


def _label(evaluations: dict) -> str:
    """A method's variant (``config.VARIANTS``) or, for a baseline, its label."""
    return next(iter(evaluations.values()))[0]["label"]


def _order(found: dict) -> list[str]:
    """End-to-end methods first (by name), then the baselines."""
    baseline = lambda method: _label(found[method]) not in config_lib.VARIANTS
    return sorted(found, key=lambda method: (baseline(method), method))


def _paper_rows(found: dict) -> list[tuple[str | None, str | None]]:
    """The paper's tables' layout: per variant (``config.VARIANTS`` order) our methods of it (by name), then
    the paper's own row (method None, variant); then the modular pipeline. A method that keeps only its
    checkpoints' evaluations (a superseded recipe's learning curve) is left to the learning curve."""
    shown = [m for m in _order(found) if len(_checkpoint_evaluations(found[m])) < len(found[m])]
    rows = []
    for variant in config_lib.VARIANTS:
        rows += [(m, variant) for m in shown if _label(found[m]) == variant] + [(None, variant)]
    return rows + [(m, None) for m in shown if _label(found[m]) not in config_lib.VARIANTS]


def _paper_figures(table: str) -> dict:
    """{variant: (the paper's row name, its figures)} of ``table`` ("ap_percent": {IoU: AP %} or "pose":
    {"location_m", "heading_rad"}), from ``report.PAPER_AP`` and ``report.PAPER_POSE``."""
    if table == "ap_percent":
        rows = {name: dict(zip(("0.1", "0.3", "0.5", "0.7"), ap)) for name, ap in report.PAPER_AP.items()}
    else:
        rows = {name: {"location_m": loc, "heading_rad": head} for name, (loc, head) in report.PAPER_POSE.items()}
    return {variant: (name, rows[name]) for variant, name in report.PAPER_VARIANT_ROW.items()}


def _runs_note(found: dict, methods: list[str]) -> str:
    """A line per method: its runs and the command that trained them."""
    runs = {m: len(_main_runs(found[m])) for m in methods}
    stops = {m: stopped_at(found[m]) for m in methods}
    stop = lambda m: "" if stops[m] is None else f", stopped at step {stops[m]:,} (the rate part-way down)"
    return "\n".join(
        f"- `{m}` ({runs[m]} run{'s' if runs[m] > 1 else ''}): `{command(found[m])}`{stop(m)}" for m in methods
    )


# ----------------------------------------------------------------------------- the tables


def _earlier_filter(evaluations: list[dict] | None) -> bool:
    """Whether an end-to-end model's belief among these evaluations took its pose figures from other filter
    settings than today's defaults, or from before evaluations recorded them (the modular baselines have no
    filter)."""
    return any(
        m["label"] in config_lib.VARIANTS
        and m["config"]["model"]["pose_head"] == "belief"
        and m["pose"].get("pose_filter") == "histogram"
        and m["pose"].get("filter_settings") != pose_belief.default_settings()
        for m in evaluations or []
    )


def _commands_only(evaluations: list[dict] | None) -> bool:
    """Whether an end-to-end model's belief moved by the commands alone in these evaluations (evaluated
    before the lidar odometry moved it there, which metrics.json records)."""
    return any(m["label"] in config_lib.VARIANTS and not m["pose"].get("lidar_odometry") for m in evaluations or [])


def _image_matcher(evaluations: list[dict] | None) -> bool:
    """Whether a held-out town's lidar odometry matched the bird-eye lidar image (evaluated before the
    scans: metrics.json records no ``scan_matcher``)."""
    return any(m["pose"].get("lidar_odometry") and not m["pose"].get("scan_matcher") for m in evaluations or [])


def _whole_cells(evaluations: list[dict] | None) -> bool:
    """Whether a belief's coverage among these evaluations counted its 95 % region in whole cells (evaluated
    before metrics.json recorded ``coverage95_region``)."""
    return any(m["pose"].get("coverage95") and not m["pose"].get("coverage95_region") for m in evaluations or [])


DETECTION_DRIVE_FIELDS = ("detection_drives", "detection_frames", "detection_pool")  # the pose drives' own stay


def _only_detection_changed(runs: list[dict], name: str) -> bool:
    """Whether the evaluation of ``runs`` is evaluation ``name`` with only detection's own drives changed
    (``name`` then ``_detection_drives0`` ...): the pose drives, and detection scored on them, are the same."""
    evaluation = protocol.from_metrics(runs[0], "")
    unchanged = dataclasses.replace(evaluation, changes=())
    return unchanged.name == name and all(field in DETECTION_DRIVE_FIELDS for field, _ in evaluation.changes)


def _same_drives(ev: dict, name: str):
    """The runs of evaluation ``name`` in ``ev`` ({evaluation: runs}), or, where it has none, those of one
    that changed only detection's own drives from it."""
    if name in ev:
        return ev[name]
    return next((runs for _, runs in sorted(ev.items()) if _only_detection_changed(runs, name)), None)


def _pose_runs(ev: dict, name: str):
    """Each run's evaluation ``name``, or where that run has none, one that changed only detection's own
    drives from it: the pose figures need the pose drives alone, so runs whose detection drives differ
    still count together."""
    candidates = [ev.get(name, [])] + [
        runs for n, runs in sorted(ev.items()) if n != name and _only_detection_changed(runs, name)
    ]
    by_run = {}
    for runs in candidates:
        for m in runs:
            by_run.setdefault(m["run"], m)
    return [by_run[run] for run in sorted(by_run)] or None


def localisation(found: dict) -> str:
    """The paper's Table II: town 0 under the global protocol, each variant beside the paper's row, then the
    modular pipeline; with what the paper lacks: the frames within 5 and 10 m, the belief's coverage, and
    the known-start protocol's error and drift on towns 0, 7 and 8 beside dead reckoning's."""
    towns = held_out_towns(found)
    header = [
        "method",
        "location mean / p90 (m)",
        "heading (rad)",
        "within 5 / 10 m (%)",
        "truth in 95 % region: place / + heading (%)",
        "known start: error at frames 100-999 / 1,000+ (m)",
        "known-start drift per 100 m: town 0 / " + " / ".join(map(str, towns)) + " (m)",
        "against the paper's row: location / heading",
    ]
    rows, shown, constant, paper, marked = [], [], None, _paper_figures("pose"), False
    commands_only = image_matcher = town0_commands = whole_cells = False
    for method, variant in _paper_rows(found):
        if method is None:
            if variant in paper:
                name, p = paper[variant]
                rows.append([f"paper: {name}", f"{p['location_m']}", f"{p['heading_rad']}", "", "", "", "", ""])
            continue
        ev = found[method]
        known = _pose_runs(ev, "eval_known_start")
        held_out = [_pose_runs(ev, f"eval_town{t}_known_start") for t in towns]
        drift = [_cell(known, "drift per 100 m (m)", digits=2, interval="drift_per_100m")] + [
            _cell(e, "drift per 100 m (m)", digits=2, interval="drift_per_100m")
            + (COMMANDS_ONLY if _commands_only(e) else "")
            + (IMAGE_MATCHER if _image_matcher(e) else "")
            for e in held_out
        ]
        commands_only = commands_only or any(map(_commands_only, held_out))
        image_matcher = image_matcher or any(map(_image_matcher, held_out))
        glob_ = _pose_runs(ev, "eval")
        against = ""
        if glob_ and variant in paper:
            mean = mean_std([summary_metrics(m) for m in glob_])
            p = paper[variant][1]
            pairs = (("location mean (m)", "location_m"), ("heading mean (rad)", "heading_rad"))
            against = " / ".join("better" if mean[k][0] <= p[f] else "worse" for k, f in pairs)
        earlier = _earlier_filter(glob_) or _earlier_filter(known)
        on_commands = _commands_only(glob_) or _commands_only(known)
        row = [
            f"`{method}`{EARLIER_FILTER if earlier else ''}{TOWN0_COMMANDS if on_commands else ''}",
            " / ".join(
                filter(
                    None,
                    [
                        _cell(glob_, "location mean (m)", interval="location_m_mean"),
                        _cell(glob_, "location p90 (m)", interval="location_m_p90"),
                    ],
                )
            ),
            _cell(glob_, "heading mean (rad)", digits=3, interval="heading_rad_mean"),
            " / ".join(
                filter(
                    None,
                    [_cell(glob_, f"location within {m} m (%)", interval=f"location_within_{m}m") for m in (5, 10)],
                )
            ),
            " / ".join(
                filter(
                    None,
                    [
                        _cell(glob_, "truth in the 95 % region, place (%)", interval="coverage_place"),
                        _cell(
                            glob_, "truth in the 95 % region, place + heading (%)", interval="coverage_place_heading"
                        ),
                    ],
                )
            )
            + (WHOLE_CELLS if _whole_cells(glob_) else ""),
            " / ".join(filter(None, [_frames_cell(known, span) for span in metrics_lib.FRAME_SPANS])),
            " / ".join(d or "-" for d in drift) if any(drift) else "",
            against,
        ]
        if not any(row[1:]):
            continue  # a method without a pose (a detector, a tracker)
        shown.append(method)
        rows.append(row)
        marked = marked or earlier
        town0_commands = town0_commands or on_commands
        whole_cells = whole_cells or _whole_cells(glob_)
        if glob_ and constant is None:
            constant = glob_[0]["baseline"]["pose"]
    if constant is not None:
        rows.append(
            [
                "constant pose (the drive's mean pose)",
                f"{constant['location_m']['mean']:.1f} / {constant['location_m']['p90']:.1f}",
                f"{constant['heading_rad']['mean']:.3f}",
                *[""] * 5,
            ]
        )
    note = f"\n{EARLIER_FILTER_NOTE}" if marked else ""
    note += f"\n{TOWN0_COMMANDS_NOTE}" if town0_commands else ""
    note += f"\n{WHOLE_CELLS_NOTE}" if whole_cells else ""
    note += f"\n{COMMANDS_ONLY_NOTE}" if commands_only else ""
    note += f"\n{IMAGE_MATCHER_NOTE}" if image_matcher else ""
    return markdown_table(header, rows) + "\n\n" + _runs_note(found, shown) + note + "\n"


def detection(found: dict) -> str:
    """The paper's Table I: AP on town 0 at every IoU, each variant beside the paper's row, then the modular
    pipeline; with what the paper lacks: visible and occluded AP, and AP@0.5 on the held-out towns."""
    ious, towns = ("0.1", "0.3", "0.5", "0.7"), held_out_towns(found)
    header = [
        "method",
        *(f"AP@{iou} (%)" for iou in ious),
        "visible AP@0.5 (%)",
        "occluded AP@0.1 / 0.5 (%)",
        "AP@0.5 town " + " / ".join(map(str, towns)) + " (%)",
        "against the paper's row",
    ]
    methods, rows, paper = [], [], _paper_figures("ap_percent")
    for method, variant in _paper_rows(found):
        if method is None:
            if variant in paper:
                name, ap = paper[variant]
                rows.append([f"paper: {name}", *(f"{ap[iou]}" for iou in ious), "", "", "", ""])
            continue
        # the evaluations that split by lidar returns alone (the others are in the groups' table)
        ev = {name: runs for name, runs in found[method].items() if not any(map(_by_group, runs))}
        town0 = ev.get("eval") or ev.get("eval_known_start")
        if town0 is None or not mean_std([summary_metrics(m) for m in town0])["AP@0.5 all (%)"][0]:
            continue  # a method without boxes (an odometry, the pose regressor)
        # detection is the same under either protocol: a run's held-out town counts under whichever it has
        held_out_ap = {}  # {town: (mean, std, runs)} of AP@0.5, for the towns the method was evaluated on
        for t in towns:
            if runs := ev.get(f"eval_town{t}", []) + ev.get(f"eval_town{t}_known_start", []):
                held_out_ap[t] = mean_std([summary_metrics(m) for m in runs]).get("AP@0.5 all (%)", (None, None, 0))
        held_out = [_format(*held_out_ap.get(t, (None, None, 0))) for t in towns]
        against = ""
        if variant in paper:
            below = _below_paper(town0, paper[variant][1], ious)
            # the held-out towns have AP@0.5 only, against the paper's one figure (its towns are not ours)
            towns_below = [
                str(t) for t, (ap, _, _) in held_out_ap.items() if ap is not None and ap < paper[variant][1]["0.5"]
            ]
            parts = ([f"below at IoU {', '.join(below)}"] if below else []) + (
                [f"town {' and '.join(towns_below)} below at IoU 0.5"] if towns_below else []
            )
            against = "; ".join(parts) or "at or above at every IoU"
        methods.append(method)
        rows.append(
            [
                f"`{method}`",
                *(_cell(town0, f"AP@{iou} all (%)") for iou in ious),
                _cell(town0, "AP@0.5 visible (%)"),
                " / ".join([_cell(town0, "AP@0.1 occluded (%)"), _cell(town0, "AP@0.5 occluded (%)")]),
                " / ".join(h or "-" for h in held_out),
                against,
            ]
        )
    return markdown_table(header, rows) + "\n\n" + _runs_note(found, methods) + "\n"


# The flags by which the paper's comparison varies a recipe: what is compared (the variant, the latent, a
# baseline and the place stream it goes without) and the seed. A method whose command adds any other flag
# is a lever on top of the recipe, left to the groups' and the targets' tables.
COMPARED_FLAGS = (
    "--config=",
    "--model.variant=",
    "--model.latent=",
    "--baseline=",
    "--data.place_frames=0",
    "--train.seed=",
)


def _compared(evaluations: dict) -> bool:
    """Whether a method's runs are its preset's recipe varied only by :data:`COMPARED_FLAGS`."""
    flags_ = command(evaluations).split()[2:]  # after "python experiments/<launcher>.py"
    return all(f.startswith(COMPARED_FLAGS) for f in flags_)


def comparison(found: dict) -> str:
    """The paper's Table I in the protocol that splits detection by who saw each box: per variant, with either
    latent, then the paper's row, then the modular pipeline; town 0, methods trained at the recipe of their
    preset (:func:`_compared`) and scored on detection's own drives, all boxes at every IoU and the lidar,
    remembered and unseen groups, each AP with its interval over drives."""
    ious = ("0.1", "0.3", "0.5", "0.7")
    header = [
        "method",
        "latent",
        *(f"AP@{iou} (%)" for iou in ious),
        "lidar AP@0.5 (%)",
        "remembered AP@0.1 (%)",
        "unseen AP@0.1 (%)",
        "against the paper's row",
    ]
    methods, rows, paper, shown = [], [], _paper_figures("ap_percent"), set()
    for method, variant in _paper_rows(found):
        if method is None:
            if variant in shown:
                name, ap = paper[variant]
                rows.append([f"paper: {name}", "", *(f"{ap[iou]}" for iou in ious), "", "", "", ""])
            continue
        runs = _group_runs(found[method], 0)
        cfg = runs and config_lib.Config.from_dict(runs[0]["config"])
        # detection's own drives (the pose drives' few boxes are in the groups' table), and boxes found
        if not runs or not cfg.eval.detection_drives or not _compared(found[method]):
            continue
        against = ""
        if variant in paper:
            below = _below_paper(runs, paper[variant][1], ious)
            against = f"below at IoU {', '.join(below)}" if below else "at or above at every IoU"
        latent = cfg.model.latent if variant else ""
        methods.append(method)
        shown.add(variant)
        rows.append(
            [
                f"`{method}`",
                latent,
                *(_interval_cell(runs, iou, "all") for iou in ious),
                _interval_cell(runs, "0.5", "lidar"),
                _interval_cell(runs, "0.1", "remembered"),
                _interval_cell(runs, "0.1", "unseen"),
                against,
            ]
        )
    if not rows:
        return "No kept evaluation of the paper's comparison splits detection by who saw each box yet.\n"
    return markdown_table(header, rows) + "\n\n" + _runs_note(found, methods) + "\n"


def _below_paper(evaluations: list[dict], paper_ap: dict, ious: tuple) -> list[str]:
    """The IoUs at which the runs' mean AP over all boxes is under the paper's row ``paper_ap`` ({iou: %})."""
    mean = mean_std([summary_metrics(m) for m in evaluations])
    return [iou for iou in ious if mean[f"AP@{iou} all (%)"][0] < paper_ap[iou]]


def _by_group(metrics: dict) -> bool:
    """Whether an evaluation splits detection by who saw each box (``metrics.GROUPS``, with intervals over
    drives), not by lidar returns alone as before."""
    return "groups" in metrics["detection"]


def _interval_cell(evaluations: list[dict], iou: str, subset: str) -> str:
    """Mean ± std over the runs of an AP (%), then in brackets the 95 % interval over drives of one run (its
    bounds averaged over the runs)."""
    ap = _cell(evaluations, f"AP@{iou} {subset} (%)")
    return ap and ap + _bounds(evaluations, lambda m: m["detection"]["ap_interval95"][iou][subset], 100.0, 1)


def _group_runs(ev: dict, town: int):
    """A method's runs of its evaluation on ``town`` that splits detection by who saw each box (under either
    pose protocol: detection is the same), or None."""
    names = ("eval", "eval_known_start") if town == 0 else (f"eval_town{town}", f"eval_town{town}_known_start")
    return next((r for r in (_same_drives(ev, n) or [] for n in names) if r and all(map(_by_group, r))), None)


def groups(found: dict) -> str:
    """Detection by who saw each box: per method and town, AP at every IoU over all boxes and per group
    (``metrics.GROUPS``), with the boxes each holds and the intervals over drives; the evaluations of the
    protocol with detection's own drives only."""
    ious, towns = ("0.1", "0.3", "0.5", "0.7"), held_out_towns(found)
    header = ["method", "town", "boxes (drives)", *(f"AP@{iou} (%)" for iou in ious)]
    rows, methods = [], []
    for method in _order(found):
        ev = found[method]
        for town in (0, *towns):
            runs = _group_runs(ev, town)
            if not runs or not mean_std([summary_metrics(m) for m in runs])["AP@0.5 all (%)"][0]:
                continue
            for subset in ("all", *runs[0]["detection"]["groups"]):
                count = runs[0]["detection"]["num_gt"][subset]
                drives = runs[0]["detection"]["num_drives_with_boxes"][subset]
                rows.append(
                    [
                        f"`{method}`" if subset == "all" else "",
                        str(town) if subset == "all" else "",
                        f"{subset.replace('_', ' ')}: {count:,} ({drives})",
                        *(_interval_cell(runs, iou, subset) for iou in ious),
                    ]
                )
            methods += [] if method in methods else [method]
    if not rows:
        return "No kept evaluation splits detection by who saw each box yet.\n"
    return markdown_table(header, rows) + "\n\n" + _runs_note(found, methods) + "\n"


# The latent that remembers, against its targets at one training recipe: the boxes the lidar sees found at
# least as well as the single-frame detector finds them, at every IoU; the remembered ones at AP@0.1 of at
# least REMEMBERED_TARGET and TRACKER_MARGIN points above the Kalman tracker's; town 0's global localisation
# within LOCATION_TARGET_M and HEADING_TARGET_RAD.
REMEMBERED_TARGET, TRACKER_MARGIN = 50.0, 10.0  # AP@0.1 (%), points
LOCATION_TARGET_M, HEADING_TARGET_RAD = 2.0, 0.03


def _recipe(metrics: dict) -> tuple:
    """What two methods' runs must share for their figures to be compared: steps, rate schedule, image size."""
    cfg = metrics["config"]
    return cfg["train"]["num_steps"], cfg["train"]["lr_decay_share"], cfg["data"]["image_size"]


def targets(found: dict) -> str:
    """Each end-to-end method on town 0 (the evaluations split by who saw each box) against the targets of a
    latent that remembers, beside the single-frame detector and the tracker trained at its recipe; the
    targets it misses, named with the figure it misses."""
    ious = ("0.1", "0.3", "0.5", "0.7")
    # detection's own drives of the protocol (a run that scored detection elsewhere is in the groups' table)
    town0 = {
        m: runs
        for m in _order(found)
        if (runs := found[m].get("eval") or found[m].get("eval_known_start")) and all(map(_by_group, runs))
    }
    means = {m: mean_std([summary_metrics(x) for x in runs]) for m, runs in town0.items()}
    town0 = {m: runs for m, runs in town0.items() if means[m]["AP@0.5 all (%)"][0]}  # methods with boxes

    def anchor(is_it, runs):  # the baseline method trained at the recipe of ``runs``, or None
        return next(
            (m for m, r in town0.items() if is_it(_label(found[m])) and _recipe(r[0]) == _recipe(runs[0])), None
        )

    header = [
        "method",
        "lidar AP@" + " / ".join(ious) + " (%)",
        "remembered AP@0.1 / 0.5 (%)",
        "location (m) / heading (rad)",
        "targets missed",
    ]
    rows = []
    for method, runs in town0.items():
        end_to_end = _label(found[method]) in config_lib.VARIANTS
        mean = lambda row, m=method: means[m][row][0]
        missed = []
        if end_to_end:
            detector = anchor(lambda label: label == baselines_lib.LABELS["detector"], runs)
            tracker = anchor(lambda label: label.startswith(baselines_lib.LABELS["tracker"]), runs)
            if detector is None:
                missed.append("lidar: no detector at this recipe")
            else:
                below = [iou for iou in ious if mean(f"AP@{iou} lidar (%)") < mean(f"AP@{iou} lidar (%)", detector)]
                if below:
                    missed.append(f"lidar at IoU {', '.join(below)} (under `{detector}`)")
            bar, bars = REMEMBERED_TARGET, [f"{REMEMBERED_TARGET:.0f} %"]
            if tracker is None:
                missed.append("remembered: no tracker at this recipe")
            else:
                bar = max(bar, mean("AP@0.1 remembered (%)", tracker) + TRACKER_MARGIN)
                bars.append(f"`{tracker}` + {TRACKER_MARGIN:.0f} points")
            if mean("AP@0.1 remembered (%)") < bar:
                missed.append(f"remembered AP@0.1 ({' and '.join(bars)})")
            if mean("location mean (m)") > LOCATION_TARGET_M:
                missed.append(f"location ({LOCATION_TARGET_M} m)")
            if mean("heading mean (rad)") > HEADING_TARGET_RAD:
                missed.append(f"heading ({HEADING_TARGET_RAD} rad)")
        rows.append(
            [
                f"`{method}`",
                " / ".join(_cell(runs, f"AP@{iou} lidar (%)") for iou in ious),
                " / ".join(_cell(runs, f"AP@{iou} remembered (%)") for iou in ("0.1", "0.5")),
                " / ".join(
                    filter(None, [_cell(runs, "location mean (m)"), _cell(runs, "heading mean (rad)", digits=3)])
                ),
                ("; ".join(missed) or "none") if end_to_end else "",
            ]
        )
    if not rows:
        return "No kept evaluation splits detection by who saw each box yet.\n"
    return markdown_table(header, rows) + "\n\n" + _runs_note(found, list(town0)) + "\n"


def learning_curve(found: dict) -> str:
    """Town 0 under the global protocol at each kept checkpoint (a run's ``eval_step<N>`` evaluations)."""
    curves = {}
    for method in _order(found):
        steps = _checkpoint_evaluations(found[method])
        if steps:
            curves[method] = steps
    if not curves:
        return "(no run keeps evaluations of its checkpoints)\n"
    header = ["training steps", *(f"`{m}`: location (m) / heading (rad) / AP@0.5 (%)" for m in curves)]
    rows = [
        [
            f"{step:,}",
            *(
                " / ".join(
                    filter(
                        None,
                        [
                            _cell(c.get(step), "location mean (m)"),
                            _cell(c.get(step), "heading mean (rad)", digits=3),
                            _cell(c.get(step), "AP@0.5 all (%)"),
                        ],
                    )
                )
                for c in curves.values()
            ),
        ]
        for step in sorted(set().union(*curves.values()))
    ]
    # the runs trained to the last kept step, evaluated at each checkpoint on the way
    last = {m: {"eval": c[max(c)]} for m, c in curves.items()}
    return markdown_table(header, rows) + "\n\n" + _runs_note(last, list(curves)) + "\n"


def _evaluations_by_step(evaluations: dict) -> dict:
    """{training step: [metrics per run]} of a method's town-0 global evaluations: each checkpoint's
    ``eval_step<N>``, and ``eval`` at the step its runs were trained to."""
    steps = _checkpoint_evaluations(evaluations)
    for m in evaluations.get("eval", []):
        if _trained_steps(m) not in steps:
            steps.setdefault(_trained_steps(m), []).append(m)
    return steps


def figure(results_dir: str):
    """uint8 BGR picture, 2 x 2 charts against training steps, one line per method (the mean over its runs):
    from the kept training records, the -ELBO (reconstructions and KL) and the place term over its weight,
    which recipes weigh differently; from the kept evaluations, town 0's location error and AP@0.5. A
    method without the output (no record, no pose, no boxes) is left out of that chart."""
    found, training = load(results_dir), load_training(results_dir)
    methods = [m for m in _order(found) if m in training or _evaluations_by_step(found[m])]
    colour = dict(zip(methods, COLOURS * 2))

    def trained(value):  # mean over a method's runs at the steps they all logged
        series = []
        for m in methods:
            runs = training.get(m, [])
            weight = _main_runs(found[m])[0]["config"]["train"]["pose_weight"]
            steps = sorted(set.intersection(*({r["step"] for r in run} for run in runs))) if runs else []
            by_step = [{r["step"]: r for r in run} for run in runs]
            series.append((m, steps, [np.mean([value(r[s], weight) for r in by_step]) for s in steps]))
        return series

    def evaluated(row):
        series = []
        for m in methods:
            by_step = _evaluations_by_step(found[m])
            means = [mean_std([summary_metrics(x) for x in by_step[s]])[row][0] for s in sorted(by_step)]
            series.append((m, sorted(by_step), [np.nan if v is None else v for v in means]))
        return series

    elbo = lambda r, w: sum(v for k, v in r.items() if k.startswith("recon_") or k == "kl")  # a variant's own terms
    charts = [
        (trained(elbo), "training: -ELBO (reconstructions + KL)", None),
        (trained(lambda r, w: r.get("pose_place", np.nan) / w), "training: place term / pose weight", None),
        (evaluated("location mean (m)"), "town 0: location error (m)", None),
        (evaluated("AP@0.5 all (%)"), "town 0: AP@0.5 (%)", (0.0, 100.0)),
    ]
    last = max([s for series, _, _ in charts for _, steps, _ in series for s in steps], default=1)
    views = []
    for series, title, y_range in charts:
        shown = [
            (m, colour[m], steps, ys) for m, steps, ys in series if np.isfinite(ys).any() and np.nanmax(np.abs(ys)) > 0
        ]  # NaN or AP 0: no such output
        log = y_range is None
        if log:  # whole decades around the values
            values = np.array([v for *_, ys in shown for v in ys if np.isfinite(v) and v > 0]) if shown else np.ones(1)
            lo = np.floor(np.log10(values.min()))
            y_range = 10.0**lo, 10.0 ** max(np.ceil(np.log10(values.max())), lo + 1)
        views.append(pictures.line_chart(shown, title, "training steps", (0, last), y_range, log_y=log))
    height = max(v.shape[0] for v in views)  # legends of more rows make taller charts
    views = [np.pad(v, ((0, height - v.shape[0]), (0, 0), (0, 0)), constant_values=255) for v in views]
    return np.concatenate([np.concatenate(views[:2], 1), np.concatenate(views[2:], 1)], 0)


TABLES = {
    "localisation": localisation,
    "detection": detection,
    "comparison": comparison,
    "groups": groups,
    "targets": targets,
    "learning_curve": learning_curve,
}


def render(results_dir: str) -> dict:
    """{table name: markdown} of the kept evaluations."""
    found = load(results_dir)
    if not found:
        raise ValueError(f"--results={results_dir}: no kept evaluations (<method>/<run>/<evaluation>.json)")
    return {name: make(found) for name, make in TABLES.items()}


def fill(text: str, tables: dict) -> str:
    """``text`` with each ``<!-- table:<name>:begin -->`` ... ``end`` block holding its table."""
    for name, table in tables.items():
        begin, end = f"<!-- table:{name}:begin -->", f"<!-- table:{name}:end -->"
        if text.count(begin) != 1 or text.count(end) != 1:
            raise ValueError(f"--readme: expected one {begin} ... {end} block")
        head, rest = text.split(begin)
        text = head + begin + "\n" + table + rest[rest.index(end) :]
    return text


def main(argv):
    try:
        if len(argv) > 1:
            raise ValueError(f"unexpected arguments {argv[1:]}")
        for spec in FLAGS.collect:
            method, _, runs = spec.partition("=")
            if not runs:
                raise ValueError(f"--collect={spec}: expected METHOD=RUN_DIR[,RUN_DIR...]")
            for path in collect(method, runs.split(","), FLAGS.results):
                print(f"kept {path}")
        tables = render(FLAGS.results)
        if FLAGS.figure:
            if not cv2.imwrite(FLAGS.figure, figure(FLAGS.results)):
                raise ValueError(f"--figure={FLAGS.figure}: could not write it (a .png path in an existing folder?)")
            print(f"wrote {FLAGS.figure}")
        if FLAGS.readme is None:
            print("\n\n".join(tables.values()))
            return
        with open(FLAGS.readme) as f:
            text = f.read()
        filled = fill(text, tables)
    except (ValueError, OSError) as e:
        sys.exit(f"error: {e}")
    if FLAGS.check:
        sys.exit(
            0
            if filled == text
            else f"{FLAGS.readme}: its tables differ from those of {FLAGS.results}; "
            f"run python experiments/tables.py --readme={FLAGS.readme}"
        )
    with open(FLAGS.readme, "w") as f:
        f.write(filled)
    print(f"wrote {len(tables)} tables into {FLAGS.readme}")


if __name__ == "__main__":
    app.run(main)
