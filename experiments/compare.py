"""One table: the end-to-end variants against the modular pipeline, on every town evaluated.

    python experiments/compare.py --sweep_dir=runs/repro --baselines_dir=runs/baselines [--out=runs/compare.md]

Reads every ``eval*/metrics.json`` under ``SWEEP_DIR/<variant>-seed<seed>/`` (sweep.py, main.py) and
``BASELINES_DIR/<baseline>/`` (baselines.py) and writes a markdown table: a row per metric, a column per
method, each cell ``training town / held-out town / ...`` (the mean over seeds where a variant has
several). The last column is the oracle constant pose of the same evaluations (no boxes). Each town's evaluations
must share one evaluation protocol (frames, worlds, start keys) and one training budget (world, data,
steps): a mismatch is an error naming the two runs, since their numbers would not be comparable.
"""

import dataclasses
import glob
import json
import os
import sys

from absl import app, flags

from e2e_percep_jax import config as config_lib
from e2e_percep_jax.config import BASELINES
from e2e_percep_jax.summary import markdown_table, mean_std, summary_metrics

CONSTANT = "constant pose"

flags.DEFINE_string("sweep_dir", None, "a sweep.py directory of <variant>-seed<seed> runs")
flags.DEFINE_string("baselines_dir", None, "a baselines.py directory of <baseline> runs")
flags.DEFINE_string("out", None, "markdown file to write (default: print only)")
FLAGS = flags.FLAGS


def _load(path):
    with open(path) as f:
        return json.load(f)


def collect(sweep_dir: str | None, baselines_dir: str | None) -> dict:
    """{method: {town_seed: [(path, metrics), ...]}} of every evaluation found (one per seed)."""
    found = {}

    def add(method, path):
        m = _load(path)
        found.setdefault(method, {}).setdefault(m["config"]["eval"]["town_seed"], []).append((path, m))

    if sweep_dir:
        for variant in config_lib.VARIANTS:
            for path in sorted(glob.glob(os.path.join(sweep_dir, f"{variant}-seed*", "eval*", "metrics.json"))):
                add(variant, path)
    if baselines_dir:
        for baseline in BASELINES:
            for path in sorted(glob.glob(os.path.join(baselines_dir, baseline, "eval*", "metrics.json"))):
                add(baseline, path)
    return found


def _protocol(m):
    """What must match for two evaluations of one town to be compared: eval protocol and training budget
    (the place stream aside: it trains the belief head alone, which the modular pipeline lacks)."""
    c = config_lib.Config.from_dict(m["config"])  # a field added since takes its default
    return {
        "eval": c.eval,
        "world": c.world,
        "data": dataclasses.replace(c.data, place_frames=0),
        "train.num_steps": c.train.num_steps,
    }


def check_comparable(found: dict) -> None:
    """Raises ValueError naming two evaluations of one town that differ in protocol or budget."""
    first = {}
    for method in found:
        for town, evals in found[method].items():
            for path, m in evals:
                protocol = _protocol(m)
                ref_path, ref = first.setdefault(town, (path, protocol))
                if protocol != ref:
                    diff = sorted(k for k in ref if ref[k] != protocol[k])
                    raise ValueError(f"{path} and {ref_path} differ in {', '.join(diff)}: not comparable")


def table(found: dict) -> str:
    """The markdown table (see the module docstring)."""
    methods = [m for m in (*config_lib.VARIANTS, *BASELINES) if m in found]
    if not methods:
        raise ValueError(
            "no evaluations found (expected SWEEP_DIR/<variant>-seed<s>/eval*/metrics.json or "
            "BASELINES_DIR/<baseline>/eval*/metrics.json)"
        )
    training_town = next(iter(found[methods[0]].values()))[0][1]["config"]["world"]["town_seed"]
    towns = sorted({t for m in methods for t in found[m]}, key=lambda t: (t != training_town, t))
    # one evaluation per town for what all of that town's share: its worlds, boxes and oracle constant
    any_eval = {t: next(m for method in methods for _, m in found[method].get(t, [])) for t in towns}
    rows = [r for r in summary_metrics(any_eval[towns[0]]) if "median" not in r]  # every AP; pose means
    cells = {}  # (row, column) -> [value per town]
    for method in methods:
        for town in towns:
            evals = [summary_metrics(m) for _, m in found[method].get(town, [])]
            means = mean_std(evals) if evals else {}
            for row in rows:
                cells.setdefault((row, method), []).append(means[row][0] if means else None)
    for town in towns:  # no boxes: AP 0 at every IoU and subset the evaluations report
        no_boxes = {iou: dict.fromkeys(by_subset, 0.0) for iou, by_subset in any_eval[town]["detection"]["ap"].items()}
        constant = summary_metrics({"detection": {"ap": no_boxes}, "pose": any_eval[town]["baseline"]["pose"]})
        for row in rows:
            cells.setdefault((row, CONSTANT), []).append(constant[row])
    fmt = lambda row, v: "n/a" if v is None else f"{v:.1f}" if row.startswith("AP") or abs(v) >= 10 else f"{v:.3g}"
    columns = [*methods, CONSTANT]
    header = [
        f"Towns {' / '.join(map(str, towns))} (town {training_town} trained on); each cell lists "
        "them in that order. Mean over seeds; runs (seeds) per method and town: "
        + ", ".join(f"{m} {'/'.join(str(len(found[m].get(t, []))) for t in towns)}" for m in methods)
        + ".",
        "",
        "Ground-truth boxes: "
        + "; ".join(
            f"town {t} "
            + ", ".join(f"{s.replace('_', ' ')} {n}" for s, n in any_eval[t]["detection"]["num_gt"].items())
            for t in towns
        )
        + ".",
        "",
    ]
    body = [[row] + [" / ".join(fmt(row, v) for v in cells[(row, c)]) for c in columns] for row in rows]
    return "\n".join(header) + "\n" + markdown_table(["metric", *columns], body) + "\n"


def main(argv):
    try:
        if len(argv) > 1:
            raise ValueError(f"unexpected arguments {argv[1:]}")
        if not (FLAGS.sweep_dir or FLAGS.baselines_dir):
            raise ValueError("--sweep_dir / --baselines_dir: give at least one")
        for name in ("sweep_dir", "baselines_dir"):
            if FLAGS[name].value and not os.path.isdir(FLAGS[name].value):
                raise ValueError(f"--{name}={FLAGS[name].value}: not a directory")
        found = collect(FLAGS.sweep_dir, FLAGS.baselines_dir)
        check_comparable(found)
        text = table(found)
    except ValueError as e:
        sys.exit(f"error: {e}")
    if FLAGS.out:
        with open(FLAGS.out, "w") as f:
            f.write(text)
    print(text)


if __name__ == "__main__":
    app.run(main)
