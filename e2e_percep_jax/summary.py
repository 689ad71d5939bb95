"""Tables over evaluations: the numbers of one ``metrics.json`` as a row, and mean ± std over seeds.

Used by ``experiments/sweep.py`` (variants x seeds) and ``experiments/compare.py`` (the end-to-end
variants against the modular baselines, per town). Plain NumPy: it reads JSON and compiles nothing.
"""

import math

import numpy as np


def defined(value):
    """None for an undefined number (None, or NaN: a head the evaluated method lacks)."""
    return None if value is None or not math.isfinite(value) else value


def summary_metrics(metrics: dict) -> dict:
    """The table's numbers from one evaluation's metrics.json: AP (%) and pose errors (None: undefined)."""
    row = {}
    for iou, by_subset in metrics["detection"]["ap"].items():  # the evaluation's IoUs and subsets, in order
        for subset, ap in by_subset.items():
            ap = defined(ap)
            row[f"AP@{iou} {subset} (%)"] = None if ap is None else 100.0 * ap
    pose = metrics["pose"]
    for name, unit in (("location", "m"), ("heading", "rad"), ("speed", "mps")):
        for stat in ("mean", "median", "p90"):  # evaluations saved before p90 existed: None
            row[f"{name} {stat} ({unit.replace('mps', 'm/s')})"] = defined(pose[f"{name}_{unit}"].get(stat))
        errors_defined = defined(pose[f"{name}_{unit}"].get("mean")) is not None
        for bound, share in pose[f"{name}_{unit}"].get("within", {}).items():  # none within a bound of no error
            defined_share = errors_defined and defined(share) is not None
            row[f"{name} within {bound} {unit} (%)"] = 100.0 * share if defined_share else None
    row["drift per 100 m (m)"] = defined(pose.get("drift_per_100m"))
    for region, share in (pose.get("coverage95") or {}).items():  # evaluations saved before it: absent
        row[f"truth in the 95 % region, {region.replace('_', ' + ')} (%)"] = 100.0 * share
    return row


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A Markdown table: the header row, its rule, a line per row (every table of the reports and the README)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


def mean_std(rows: list) -> dict:
    """{metric: (mean, std, n)} over runs, ignoring runs where the metric is undefined (None)."""
    out = {}
    for key in rows[0]:
        values = np.array([r[key] for r in rows if r.get(key) is not None], np.float64)
        out[key] = (float(values.mean()), float(values.std()), len(values)) if len(values) else (None, None, 0)
    return out
