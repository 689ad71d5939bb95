"""The tables launcher: its cells against means and standard deviations worked out by hand, the kept
evaluations without their curves, the README's blocks filled, and the README's tables equal to what the
kept evaluations render (so the README cannot drift from the runs)."""

import json
import os
import subprocess
import sys

import pytest
from helpers import ROOT, load_experiment

from e2e_percep_jax import config, pose_belief, protocol

tables = load_experiment("tables")


def _metrics(
    seed,
    *,
    label="full",
    ap=0.5,
    location=4.0,
    drift=1.0,
    town=0,
    known_start=False,
    by_step=(3.0, 3.0),
    step=None,
    place_frames=None,
    earlier_filter=False,
    commands_only=False,
    image_matcher=False,
    whole_cells=False,
):
    """A metrics.json with what the tables read, every AP ``ap`` and the location mean ``location``
    (of checkpoint ``step``, or of the trained run where None), of the `cpu` preset (with ``place_frames``
    where given: another recipe), its belief filtered at today's defaults (``earlier_filter``: from before
    evaluations recorded the filter's settings), on a held-out town from the known start by the lidar
    odometry (``commands_only``: from before evaluations recorded it; ``image_matcher``: its matcher on the
    lidar images, from before evaluations recorded what it matched), its regions holding exactly 95 %
    (``whole_cells``: from before evaluations recorded how the region was counted)."""
    cfg = config.replace(
        config.get_config("cpu"), train=dict(seed=seed), eval=dict(town_seed=town, known_start=known_start)
    )
    if place_frames is not None:
        cfg = config.replace(cfg, data=dict(place_frames=place_frames))
    if step is not None and step != cfg.train.num_steps:  # a learning curve's checkpoint: a constant rate's run
        cfg = config.replace(cfg, train=dict(lr_decay_share=0.0))
    pose = {
        "location_m": {"mean": location, "median": location, "p90": 2 * location, "within": {"5": 0.3, "10": 0.5}},
        "heading_rad": {"mean": 0.05, "median": 0.05, "p90": 0.1, "within": {}},
        "speed_mps": {"mean": 0.1, "median": 0.1, "p90": 0.2, "within": {}},
        "location_m_by_step": {
            "bin_edges": [0, 10, 30, 100, 300, 1000, 3000],
            "mean": [9.0, 9.0, 9.0, by_step[0], by_step[0], by_step[1]],
            "count": [10, 20, 70, 200, 700, 875],
        },
        "drift_per_100m": drift,
        "coverage95": {"place": 0.95, "place_heading": 0.9},
        "pose_filter": "histogram",
    }
    if not whole_cells:
        pose["coverage95_region"] = "exact mass"
    if not earlier_filter:
        pose["filter_settings"] = pose_belief.default_settings()
    if not commands_only:
        pose["lidar_odometry"] = True
        if not image_matcher:
            pose["scan_matcher"] = "lidar scan"
    return {
        "label": label,
        "config": json.loads(cfg.to_json()),
        "checkpoint_step": step,
        "detection": {
            "ap": {
                iou: {"all": ap, "visible": ap, "occluded": ap / 2} for iou in ("0.1", "0.3", "0.5", "0.7")
            },  # the earlier split
            "pr_curves": [[0.0] * 100],
        },
        "examples": [1],
        "pose": pose,
        "baseline": {
            "pose": {
                **pose,
                "location_m": {"mean": 160.0, "median": 150.0, "p90": 240.0, "within": {}},
                "heading_rad": {"mean": 1.1, "median": 1.1, "p90": 2.0, "within": {}},
            }
        },
    }


def _write_run(run_dir, evaluations):
    for name, metrics in evaluations.items():
        os.makedirs(os.path.join(run_dir, name), exist_ok=True)
        with open(os.path.join(run_dir, name, "metrics.json"), "w") as f:
            json.dump(metrics, f)


def _write_training(run_dir, seed):
    """A metrics.jsonl logged every 50 steps to 3,500 (trained on past its evaluated 3,000), resumed once
    from step 150, so steps 200 and 250 are logged twice (the second time with kl 20)."""
    os.makedirs(run_dir, exist_ok=True)
    record = lambda step, kl: json.dumps({"step": step, "recon_camera": 1000.0 + seed, "kl": kl, "pose_place": 160.0})
    lines = [record(step, 10.0) for step in range(50, 300, 50)] + [record(step, 20.0) for step in range(200, 3550, 50)]
    (run_dir / "metrics.jsonl").write_text("\n".join(lines) + "\n")


@pytest.fixture
def results(tmp_path):
    """Two seeds of `cpu` (AP 50 / 60 %, location 4 / 6 m), two more of it with only their checkpoints'
    evaluations (runs that sort first), one run of another recipe that keeps only a checkpoint's evaluation
    (`place64`: more place frames), one
    `dead_reckoning` run and one `detector` run (no pose), kept."""
    for seed, ap, location, by_step in ((0, 0.5, 4.0, (2.0, 4.0)), (1, 0.6, 6.0, (4.0, 6.0))):
        _write_training(tmp_path / "runs" / f"place_s{seed}", seed)
        _write_run(
            tmp_path / "runs" / f"place_s{seed}",
            {
                "eval": _metrics(seed, ap=ap, location=location),
                "eval_known_start": _metrics(seed, ap=ap, known_start=True, drift=0.5 + seed, by_step=by_step),
                "eval_town7_known_start": _metrics(seed, ap=ap / 2, town=7, known_start=True, drift=2.0),
            },
        )
    for seed in (0, 1):
        _write_run(
            tmp_path / "runs" / f"curve_s{seed}",
            {
                "eval_step1000": _metrics(seed, ap=0.1, location=20.0 + 10 * seed, step=1000),
                "eval_step2000": _metrics(seed, ap=0.3 + 0.2 * seed, location=5.0, step=2000),
            },
        )
    unposed = _metrics(0, label="single-frame detector", ap=0.7)  # boxes and no pose: NaN errors, 0 % within
    for name in ("location_m", "heading_rad", "speed_mps"):
        unposed["pose"][name].update(mean=float("nan"), median=float("nan"), p90=float("nan"))
    unposed["pose"].update(
        drift_per_100m=None, location_m_by_step={"bin_edges": [0, 10], "mean": [None], "count": [10]}
    )
    del unposed["pose"]["coverage95"]
    unposed["pose"]["location_m"]["within"] = {"10": 0.0}
    _write_run(tmp_path / "runs" / "detector", {"eval": unposed})
    _write_run(
        tmp_path / "runs" / "dead_reckoning",
        {"eval_known_start": _metrics(0, label="dead_reckoning", ap=0.0, known_start=True, drift=3.0)},
    )
    out = tmp_path / "results"
    tables.collect(
        "cpu", [str(tmp_path / "runs" / name) for name in ("place_s0", "place_s1", "curve_s0", "curve_s1")], str(out)
    )
    _write_run(
        tmp_path / "runs" / "place64", {"eval_step1000": _metrics(0, ap=0.2, location=9.0, step=1000, place_frames=64)}
    )
    tables.collect("place64", [str(tmp_path / "runs" / "place64")], str(out))
    tables.collect("dead_reckoning", [str(tmp_path / "runs" / "dead_reckoning")], str(out))
    tables.collect("detector", [str(tmp_path / "runs" / "detector")], str(out))
    return out


def _row(table, method):
    return next(line for line in table.splitlines() if line.startswith(f"| {method} |")).split(" | ")


def test_cells_are_the_mean_and_std_over_seeds(results):
    rendered = tables.render(str(results))
    det = _row(rendered["detection"], "`cpu`")
    # AP 50 and 60 %: mean 55, population std 5; occluded AP is half
    assert det[1:6] == ["55.0 ± 5.0"] * 5 and det[6] == "27.5 ± 2.5 / 27.5 ± 2.5" and det[7] == "27.5 ± 2.5"
    assert "AP@0.5 town 7 (%)" in rendered["detection"]  # the held-out towns the kept evaluations drove
    # 55 % against the paper's 79.4, 72.0, 56.5, 16.8 %; town 7 (27.5 %) against its 56.5 at IoU 0.5
    assert det[8] == "below at IoU 0.1, 0.3, 0.5; town 7 below at IoU 0.5 |"
    assert "`dead_reckoning`" not in rendered["detection"]  # no boxes: no detection row
    assert _row(rendered["detection"], "`detector`")[3] == "70.0"
    assert "`detector`" not in rendered["localisation"]  # no pose: no localisation row, no command line
    loc = _row(rendered["localisation"], "`cpu`")
    assert loc[1] == "5.0 ± 1.0 / 10.0 ± 2.0" and loc[2] == "0.050 ± 0.000" and loc[3] == "30.0 ± 0.0 / 50.0 ± 0.0"
    assert loc[4] == "95.0 ± 0.0 / 90.0 ± 0.0"
    # frames 100-999 are the bins 100-300 and 300-1000 (both 2 m, then 4 m); 1,000+ is the last bin
    assert loc[5] == "3.0 ± 1.0 / 5.0 ± 1.0"
    assert loc[6] == "1.00 ± 0.50 / 2.00 ± 0.00" and loc[7] == "better / better |"  # the paper: 11.4 m, 0.33 rad
    dr = _row(rendered["localisation"], "`dead_reckoning`")
    assert dr[1] == "" and dr[6] == "3.00 / -"
    assert "| constant pose (the drive's mean pose) | 160.0 / 240.0 | 1.100 |" in rendered["localisation"]
    assert (
        "- `cpu` (2 runs): `python experiments/main.py --config=cpu --train.seed={0,1}`"
        in rendered["localisation"].splitlines()
    )
    assert (
        "- `dead_reckoning` (1 run): `python experiments/baselines.py --baseline=dead_reckoning --config=cpu`"
        in rendered["localisation"].splitlines()
    )


def test_pose_cells_carry_the_interval_over_drives_where_every_run_has_one(results, tmp_path):
    """Each run's 95 % interval over drives (``pose.interval95``), its bounds averaged over the runs, follows
    the mean ± std in brackets (shares in %), the known start's error by frames too; a run without one (an
    evaluation made before intervals) leaves the cell without brackets."""
    for seed in (0, 1):
        m = _metrics(seed, location=4.0 + 2 * seed)
        m["pose"]["interval95"] = {
            "location_m_mean": [3.0 + seed, 5.0 + 2 * seed],
            "heading_rad_mean": [0.04, 0.06],
            "coverage_place": [0.9, 0.98 + 0.01 * seed],
        }
        known = _metrics(seed, known_start=True, by_step=(2.0 + seed, 3.0))
        known["pose"]["interval95"] = {"location_m_frames_100_999": [1.0, 3.0 + seed]}  # the late span's is missing
        _write_run(tmp_path / "bounded" / f"place_s{seed}", {"eval": m, "eval_known_start": known})
    tables.collect("bounded", [str(tmp_path / "bounded" / f"place_s{s}") for s in (0, 1)], str(results))
    loc = _row(tables.render(str(results))["localisation"], "`bounded`")
    assert loc[1] == "5.0 ± 1.0 [3.5, 6.0] / 10.0 ± 2.0" and loc[2] == "0.050 ± 0.000 [0.040, 0.060]"
    assert loc[4] == "95.0 ± 0.0 [90.0, 98.5] / 90.0 ± 0.0"
    assert loc[5] == "2.5 ± 0.5 [1.0, 3.5] / 3.0 ± 0.0"
    assert _row(tables.render(str(results))["localisation"], "`cpu`")[1] == "5.0 ± 1.0 / 10.0 ± 2.0"


def test_the_papers_tables_set_each_variant_beside_the_papers_row(results):
    """Our `full` runs, then the paper's `full` row, then the paper's rows of the other variants (we have no
    runs of them here), then the modular pipeline; `place64` (only a checkpoint's evaluation kept: a
    superseded recipe's curve) only in the learning curve."""
    rendered = tables.render(str(results))
    for name, first_baseline in (("detection", "`detector`"), ("localisation", "`dead_reckoning`")):
        methods = [line.split(" | ")[0][2:] for line in rendered[name].splitlines()[2:] if line.startswith("| ")]
        assert methods[:5] == [
            "`cpu`",
            "paper: Inputs and roadmap (full)",
            "paper: No inputs reconstruction (no_input_recon)",
            "paper: No roadmap reconstruction (no_roadmap_recon)",
            first_baseline,
        ], methods
        assert "place64" not in rendered[name]
    assert "`place64`" in rendered["learning_curve"]


def test_a_variant_filtered_at_earlier_settings_is_marked(results, tmp_path):
    """A variant whose town-0 known-start evaluation (one seed of two) did not record today's filter
    settings gets the mark and the note in the localisation table; with every evaluation at today's
    settings, and for a baseline (dead reckoning has no filter, and records none), neither appears."""
    localisation = tables.render(str(results))["localisation"]
    assert tables.EARLIER_FILTER not in localisation and tables.EARLIER_FILTER_NOTE not in localisation
    _write_run(tmp_path / "runs" / "place_s1", {"eval_known_start": _metrics(1, known_start=True, earlier_filter=True)})
    tables.collect("cpu", [str(tmp_path / "runs" / name) for name in ("place_s0", "place_s1")], str(results))
    localisation = tables.render(str(results))["localisation"]
    assert localisation.count(tables.EARLIER_FILTER) == 1 + tables.EARLIER_FILTER_NOTE.count(tables.EARLIER_FILTER)
    assert _row(localisation, f"`cpu`{tables.EARLIER_FILTER}")[1] == "5.0 ± 1.0 / 10.0 ± 2.0"
    assert tables.EARLIER_FILTER_NOTE in localisation


def test_a_training_town_belief_moved_by_the_commands_alone_is_marked(results, tmp_path):
    """A variant whose town-0 known-start evaluation (one seed of two) is from before the lidar odometry moved
    the belief there gets the mark on its name and the note; with every evaluation by today's, neither."""
    localisation = tables.render(str(results))["localisation"]
    assert tables.TOWN0_COMMANDS not in localisation and tables.TOWN0_COMMANDS_NOTE not in localisation
    _write_run(tmp_path / "runs" / "place_s1", {"eval_known_start": _metrics(1, known_start=True, commands_only=True)})
    tables.collect("cpu", [str(tmp_path / "runs" / name) for name in ("place_s0", "place_s1")], str(results))
    localisation = tables.render(str(results))["localisation"]
    assert _row(localisation, f"`cpu`{tables.TOWN0_COMMANDS}")[1] == "5.0 ± 1.0 / 10.0 ± 2.0"
    assert tables.TOWN0_COMMANDS_NOTE in localisation


def test_a_coverage_counted_in_whole_cells_is_marked(results, tmp_path):
    """A variant whose global evaluation (one seed of two) counted its region in whole cells gets the mark on
    its coverage cell and the note; with every evaluation counting exactly 95 %, neither appears."""
    localisation = tables.render(str(results))["localisation"]
    assert tables.WHOLE_CELLS not in localisation and tables.WHOLE_CELLS_NOTE not in localisation
    _write_run(tmp_path / "runs" / "place_s1", {"eval": _metrics(1, ap=0.6, location=6.0, whole_cells=True)})
    tables.collect("cpu", [str(tmp_path / "runs" / name) for name in ("place_s0", "place_s1")], str(results))
    localisation = tables.render(str(results))["localisation"]
    assert _row(localisation, "`cpu`")[4] == f"95.0 ± 0.0 / 90.0 ± 0.0{tables.WHOLE_CELLS}"
    assert tables.WHOLE_CELLS_NOTE in localisation


@pytest.mark.parametrize(
    "old, mark, note",
    [
        ({"commands_only": True}, tables.COMMANDS_ONLY, tables.COMMANDS_ONLY_NOTE),
        ({"image_matcher": True}, tables.IMAGE_MATCHER, tables.IMAGE_MATCHER_NOTE),
    ],
)
def test_a_held_out_drift_of_an_earlier_odometry_is_marked(results, tmp_path, old, mark, note):
    """A variant's held-out known-start evaluation (one seed of two) from before the lidar odometry (the
    commands alone), or from before it matched the lidar's scans (the image), gets its mark on that town's
    drift, and its note; with every evaluation by today's odometry, neither appears."""
    localisation = tables.render(str(results))["localisation"]
    assert mark not in localisation and note not in localisation
    _write_run(
        tmp_path / "runs" / "place_s1",
        {"eval_town7_known_start": _metrics(1, town=7, known_start=True, drift=2.0, **old)},
    )
    tables.collect("cpu", [str(tmp_path / "runs" / name) for name in ("place_s0", "place_s1")], str(results))
    localisation = tables.render(str(results))["localisation"]
    assert _row(localisation, "`cpu`")[6] == f"1.00 ± 0.50 / 2.00 ± 0.00{mark}"
    assert note in localisation


def test_learning_curve_reads_each_checkpoints_evaluations(results):
    curve = tables.render(str(results))["learning_curve"]
    assert _row(curve, "1,000")[1:] == ["25.0 ± 5.0 / 0.050 ± 0.000 / 10.0 ± 0.0", "9.0 / 0.050 / 20.0 |"]
    assert _row(curve, "2,000")[1:] == ["5.0 ± 0.0 / 0.050 ± 0.000 / 40.0 ± 10.0", " |"]  # `place64`: none
    assert "`dead_reckoning`" not in curve  # no checkpoints evaluated
    assert (
        "- `cpu` (2 runs): `python experiments/main.py --config=cpu --train.num_steps=2000 "
        "--train.lr_decay_share=0.0 --train.seed={0,1}`" in curve.splitlines()  # a constant rate's checkpoints
    )


def test_a_decaying_rate_is_in_the_command_and_a_checkpoint_inside_it_is_a_stopped_run():
    """Under ``--train.lr_decay_share`` the last checkpoint is the run its command trains; one before the decay
    starts saw a constant rate, so it is that many steps at a constant rate; one inside the decay saw a rate no
    shorter run sees: the same command, stopped there (:func:`tables.stopped_at`)."""

    def decayed(seed, step):
        m = dict(_metrics(seed, step=step), run=f"decay_s{seed}")
        m["config"]["train"].update(num_steps=9000, lr_decay_share=0.5)  # decays from step 4,500 on
        return m

    full = "python experiments/main.py --config=cpu --train.num_steps=9000 --train.lr_decay_share=0.5"
    assert tables.command({"eval": [decayed(0, 9000), decayed(1, 9000)]}) == full + " --train.seed={0,1}"
    assert tables.stopped_at({"eval": [decayed(0, 9000)]}) is None
    assert tables.command({"eval": [decayed(0, 4500)]}) == (
        "python experiments/main.py --config=cpu --train.num_steps=4500 --train.lr_decay_share=0.0"
    )
    assert tables.stopped_at({"eval": [decayed(0, 4500)]}) is None
    assert tables.command({"eval": [decayed(0, 6000)]}) == full
    assert tables.stopped_at({"eval": [decayed(0, 6000)]}) == 6000
    with pytest.raises(ValueError, match=r"stopped at different steps: \[6000, 7000\]"):
        tables.stopped_at({"eval": [decayed(0, 6000), decayed(1, 7000)]})


def test_collected_runs_are_named_by_their_path_below_the_common_folder(tmp_path):
    """A sweep keeps each seed's baselines in ``baselines-seed<s>/<baseline>``: same folder names, two runs."""
    for seed in (0, 1):
        _write_run(tmp_path / "sweep" / f"baselines-seed{seed}" / "detector", {"eval": _metrics(seed, ap=0.1 * seed)})
    written = tables.collect(
        "detector",
        [str(tmp_path / "sweep" / f"baselines-seed{s}" / "detector") for s in (0, 1)],
        str(tmp_path / "results"),
    )
    assert sorted(os.path.relpath(p, tmp_path / "results") for p in written) == [
        os.path.join("detector", f"baselines-seed{s}-detector", "eval.json") for s in (0, 1)
    ]
    assert [m["config"]["train"]["seed"] for m in tables.load(str(tmp_path / "results"))["detector"]["eval"]] == [0, 1]
    alone = tables.collect("detector", [str(tmp_path / "sweep" / "baselines-seed0" / "detector")], str(tmp_path / "r2"))
    assert alone == [str(tmp_path / "r2" / "detector" / "detector" / "eval.json")]


def test_kept_training_record_is_every_100th_step_to_the_evaluated_checkpoint(results):
    with open(results / "cpu" / "place_s0" / "training.jsonl") as f:
        kept = [json.loads(line) for line in f]
    assert [r["step"] for r in kept] == list(range(100, 3001, 100))
    assert [r["kl"] for r in kept[:2]] == [10.0, 20.0]  # step 200 as the resumed run logged it
    assert not (results / "cpu" / "curve_s0" / "training.jsonl").exists()  # no record, none kept


def test_learning_curves_figure_draws_each_method_where_it_has_the_output(results):
    """`cpu` has training records, checkpoint evaluations and a pose: a line in all four charts; the
    detector has one evaluation with boxes and no pose, and no record: only in the AP chart."""
    image = tables.figure(str(results))
    h, w = image.shape[0] // 2, image.shape[1] // 2
    charts = [image[:h, :w], image[:h, w:], image[h:, :w], image[h:, w:]]  # -ELBO, place, location, AP
    shows = lambda chart, colour: bool((chart == colour).all(-1).sum() > 30)
    cpu, detector = tables.COLOURS[0], tables.COLOURS[2]  # end-to-end methods first (`cpu`, `place64`)
    assert [shows(c, cpu) for c in charts] == [True] * 4
    assert [shows(c, detector) for c in charts] == [False, False, False, True]


def test_kept_evaluations_lose_only_their_curves(results):
    kept = json.loads((results / "cpu" / "place_s0" / "eval.json").read_text())
    assert "pr_curves" not in kept["detection"] and "examples" not in kept
    assert kept["detection"]["ap"] == _metrics(0)["detection"]["ap"] and kept["pose"] == _metrics(0)["pose"]


def test_readme_blocks_are_filled_and_checked(results, tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(
        "# x\n<!-- table:localisation:begin -->\nold\n<!-- table:localisation:end -->\ntext\n"
        "<!-- table:detection:begin --><!-- table:detection:end -->\n"
        "<!-- table:comparison:begin --><!-- table:comparison:end -->\n"
        "<!-- table:groups:begin --><!-- table:groups:end -->\n"
        "<!-- table:targets:begin --><!-- table:targets:end -->\n"
        "<!-- table:learning_curve:begin --><!-- table:learning_curve:end -->\n"
    )
    cmd = [sys.executable, os.path.join(ROOT, "experiments", "tables.py"), f"--results={results}", f"--readme={readme}"]
    stale = subprocess.run(cmd + ["--check"], capture_output=True, text=True, timeout=120)
    assert stale.returncode == 1 and "differ" in stale.stderr
    subprocess.run(cmd, check=True, capture_output=True, timeout=120)
    text = readme.read_text()
    assert "old" not in text and text.startswith("# x\n") and "\ntext\n" in text
    assert tables.render(str(results))["detection"] in text
    assert tables.fill(text, tables.render(str(results))) == text  # what --check compares: now up to date
    with pytest.raises(ValueError, match="table:localisation"):
        tables.fill("no markers", tables.render(str(results)))


def test_the_readme_shows_what_the_kept_evaluations_render():
    with open(os.path.join(ROOT, "README.md")) as f:
        text = f.read()
    assert tables.fill(text, tables.render(os.path.join(ROOT, "experiments", "results"))) == text


def test_groups_table_gives_each_group_its_boxes_seed_means_and_the_drives_interval(tmp_path):
    """Two seeds of an evaluation split by who saw each box: a row per group with its boxes and drives, each
    AP the mean ± std over the seeds and the interval over drives averaged; the earlier split stays in the
    detection table, the new one only here."""
    subsets = ("all", "lidar", "camera_only", "remembered", "unseen")
    for seed, ap in ((0, 0.5), (1, 0.6)):
        m = _metrics(seed, ap=ap)
        m["detection"] = {
            "groups": list(subsets[1:]),
            "ap": {iou: dict.fromkeys(subsets, ap) for iou in ("0.1", "0.3", "0.5", "0.7")},
            "ap_interval95": {
                iou: dict.fromkeys(subsets, [ap - 0.1, ap + 0.2]) for iou in ("0.1", "0.3", "0.5", "0.7")
            },
            "num_gt": dict(zip(subsets, (1300, 1000, 10, 90, 200))),
            "num_drives_with_boxes": dict(zip(subsets, (40, 40, 3, 25, 9))),
        }
        path = tmp_path / "cpu" / f"s{seed}" / "eval.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps(m))
    rendered = tables.render(str(tmp_path))
    rows = [line for line in rendered["groups"].splitlines() if line.startswith("| ")][1:]
    assert [r.split(" | ")[2] for r in rows] == [
        "all: 1,300 (40)",
        "lidar: 1,000 (40)",
        "camera only: 10 (3)",
        "remembered: 90 (25)",
        "unseen: 200 (9)",
    ]
    assert rows[0].startswith("| `cpu` | 0 |") and rows[3].endswith("| 55.0 ± 5.0 [45.0, 75.0] |")
    assert "`cpu`" not in rendered["detection"]


def _by_group_metrics(seed, *, label="full", lidar=0.9, remembered=0.05, location=1.5, lr_decay_share=None):
    """An evaluation split by who saw each box: lidar and remembered AP as given at every IoU."""
    m = _metrics(seed, label=label, location=location)
    if lr_decay_share is not None:
        m["config"]["train"]["lr_decay_share"] = lr_decay_share
    aps = dict(all=lidar, lidar=lidar, camera_only=0.0, remembered=remembered, unseen=0.3)
    ious = ("0.1", "0.3", "0.5", "0.7")
    m["detection"] = {
        "groups": list(aps)[1:],
        "ap": dict.fromkeys(ious, aps),
        "ap_interval95": dict.fromkeys(ious, {k: [v, v] for k, v in aps.items()}),
        "num_gt": dict.fromkeys(aps, 100),
        "num_drives_with_boxes": dict.fromkeys(aps, 10),
    }
    return m


def test_targets_name_what_each_method_misses_against_the_baselines_at_its_recipe(tmp_path):
    """The latent's targets: lidar AP at least the detector's at every IoU, remembered AP@0.1 at least 50 % and
    the tracker's + 10 points, location <= 2 m, heading <= 0.03 rad (each fixture's is 0.05); the baselines
    are those trained at the method's recipe, and a method at a recipe without them says so."""
    detector, tracker = "single-frame detector", "single-frame detector + Kalman tracker (coasting)"
    runs = {
        "detector": [_by_group_metrics(0, label=detector, lidar=0.93)],
        "tracker": [_by_group_metrics(0, label=tracker, lidar=0.92, remembered=0.45)],
        "latent": [_by_group_metrics(s, lidar=0.95, remembered=0.56 + 0.02 * s, location=1.5 + s) for s in (0, 1)],
        "weak": [_by_group_metrics(0, lidar=0.90, remembered=0.52, location=2.5)],
        "constant": [_by_group_metrics(0, lr_decay_share=0.0)],
    }
    for method, evaluations in runs.items():  # a baseline's run is named after it
        dirs = (
            [tmp_path / "runs" / method / f"s{i}" for i in range(len(evaluations))]
            if len(evaluations) > 1
            else [tmp_path / "runs" / method]
        )
        for run_dir, m in zip(dirs, evaluations):
            _write_run(run_dir, {"eval": m})
        tables.collect(method, list(map(str, dirs)), str(tmp_path / "out"))
    table = tables.render(str(tmp_path / "out"))["targets"]
    latent = _row(table, "`latent`")
    assert latent[1:4] == [
        "95.0 ± 0.0 / 95.0 ± 0.0 / 95.0 ± 0.0 / 95.0 ± 0.0",
        "57.0 ± 1.0 / 57.0 ± 1.0",
        "2.0 ± 0.5 / 0.050 ± 0.000",
    ]
    assert latent[4] == "heading (0.03 rad) |"  # 2.0 m is within the target; 57 % is over 50 % and 45 + 10
    weak = _row(table, "`weak`")[4]
    assert weak.startswith("lidar at IoU 0.1, 0.3, 0.5, 0.7 (under `detector`); remembered AP@0.1 (50 % and `tracker`")
    assert "location (2.0 m)" in weak
    assert _row(table, "`constant`")[4].startswith("lidar: no detector at this recipe; remembered: no tracker")
    assert _row(table, "`detector`")[4] == " |"  # the baselines are the bars, not measured against them


def test_the_comparison_sets_each_variant_with_either_latent_beside_the_papers_row_and_leaves_levers_out(tmp_path):
    """Table I in the groups' protocol: per variant its methods trained at the preset's recipe, with either
    latent, then the paper's row (none for a variant without a method); a method with a lever on top of the
    recipe, and one scored on the pose drives alone, are left out; every AP carries its interval."""

    def changed(m, **sections):
        return dict(m, config=json.loads(config.replace(config.Config.from_dict(m["config"]), **sections).to_json()))

    runs = {
        "grid": [_by_group_metrics(s, lidar=0.95) for s in (0, 1)],
        "vector": [changed(_by_group_metrics(0, lidar=0.7), model=dict(latent="vector"))],
        "no-roadmap": [changed(_by_group_metrics(0, label="no_roadmap_recon"), model=dict(variant="no_roadmap_recon"))],
        "lever": [changed(_by_group_metrics(0), train=dict(remembered_weight=3.0))],
        "pose-drives": [changed(_by_group_metrics(0), eval=dict(detection_drives=0))],
        "detector": [_by_group_metrics(0, label="single-frame detector", lidar=0.93)],
    }
    for method, evaluations in runs.items():  # a baseline's run is named after it
        dirs = [tmp_path / "runs" / method / f"s{i}" for i in range(len(evaluations))]
        dirs = dirs if len(dirs) > 1 else [tmp_path / "runs" / method]
        for run_dir, m in zip(dirs, evaluations):
            _write_run(run_dir, {"eval": m})
        tables.collect(method, list(map(str, dirs)), str(tmp_path / "out"))
    table = tables.render(str(tmp_path / "out"))["comparison"]
    rows = [line.split(" | ") for line in table.splitlines() if line.startswith("| ")][1:]
    assert [r[0][2:] for r in rows] == [
        "`grid`",
        "`vector`",
        "paper: Inputs and roadmap (full)",
        "`no-roadmap`",
        "paper: No roadmap reconstruction (no_roadmap_recon)",
        "`detector`",
    ]
    assert [r[1] for r in rows] == ["bev", "vector", "", "bev", "", ""]
    assert rows[0][2] == "95.0 ± 0.0 [95.0, 95.0]" and rows[1][6] == "70.0 [70.0, 70.0]"
    assert rows[0][7:9] == ["5.0 ± 0.0 [5.0, 5.0]", "30.0 ± 0.0 [30.0, 30.0]"]  # remembered, unseen at IoU 0.1
    assert rows[0][9] == "at or above at every IoU |" and rows[1][9] == "below at IoU 0.1, 0.3 |"


def test_an_evaluation_without_detections_own_drives_fills_the_pose_cells(results, tmp_path):
    """A held-out known-start evaluation that only left out detection's own drives
    (``--eval.detection_drives=0``: its protocol's name gains ``_detection_drives0``) drove the same pose
    drives, so its drift fills that town's cell, also beside another run's evaluation with detection drives of
    its own; an evaluation that changed the pose drives does not. Town 0's
    global protocol likewise, and a known start there, which also left them out, is not taken for it."""
    trained = config.get_config("cpu")

    def evaluation(seed, drift, town=7, known_start=True, location=1.0, **eval_changes):
        m = _metrics(seed, town=town, known_start=known_start, drift=drift, location=location)
        eval_cfg = dict(town_seed=town, known_start=known_start, **eval_changes)
        cfg = config.replace(trained, train=dict(seed=seed), eval=eval_cfg)
        m["protocol"] = protocol.of(cfg, config.replace(trained, train=dict(seed=seed))).to_dict()
        m["config"] = json.loads(cfg.to_json())
        return {m["protocol"]["name"]: m}

    for seed in (0, 1):
        _write_run(tmp_path / "odo" / f"place_s{seed}", evaluation(seed, 3.0 + seed, detection_drives=0))
    tables.collect("odometry", [str(tmp_path / "odo" / f"place_s{s}") for s in (0, 1)], str(results))
    assert _row(tables.render(str(results))["localisation"], "`odometry`")[6] == "- / 3.50 ± 0.50"
    # one run scored detection on drives of its own there, the other on the pose drives: both pose figures count
    _write_run(tmp_path / "mixed" / "place_s0", evaluation(0, 3.0, detection_drives=160, detection_pool=2048))
    _write_run(tmp_path / "mixed" / "place_s1", evaluation(1, 4.0, detection_drives=0))
    tables.collect("mixed", [str(tmp_path / "mixed" / f"place_s{s}") for s in (0, 1)], str(results))
    assert _row(tables.render(str(results))["localisation"], "`mixed`")[6] == "- / 3.50 ± 0.50"
    for seed in (0, 1):
        _write_run(tmp_path / "drives" / f"place_s{seed}", evaluation(seed, 3.0, num_worlds=2))
    tables.collect("drives", [str(tmp_path / "drives" / f"place_s{s}") for s in (0, 1)], str(results))
    assert "| `drives` |" not in tables.render(str(results))["localisation"]
    for seed in (0, 1):
        pose_only = dict(town=0, drift=0.5, detection_drives=0)
        _write_run(
            tmp_path / "town0" / f"place_s{seed}",
            {
                **evaluation(seed, known_start=True, location=9.0, **pose_only),
                **evaluation(seed, known_start=False, location=3.0 + seed, **pose_only),
            },
        )
    tables.collect("town0", [str(tmp_path / "town0" / f"place_s{s}") for s in (0, 1)], str(results))
    assert _row(tables.render(str(results))["localisation"], "`town0`")[1] == "3.5 ± 0.5 / 7.0 ± 1.0"
