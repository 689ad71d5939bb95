"""What memory could find: of the remembered boxes, how many belong to a vehicle found before it was hidden.

    python experiments/memory_ceiling.py --workdir=runs/cpu [--drives=40]
    python experiments/memory_ceiling.py --workdir=runs/baselines/detector --detector

A remembered box (``metrics.GROUPS``) belongs to a vehicle that some sensor saw within the last 30 frames
and none sees now. A sensor seeing it is not a perceiver finding it: one beam on a car's corner counts as
seen. Memory can keep only what was found, so this records the run's detections (``--detector``: a
single-frame detector's run) on its evaluation's detection drives (the ``--drives`` holding the most
remembered boxes) and counts, for each remembered box, whether a detection at the operating score
(``eval.score_threshold``) matched its vehicle (IoU >= 0.1, ``metrics.match_detections``) in one of the 30
frames before, and whether one matches it now: of those found before, the share found now is what the
perceiver kept. Prints JSON, the lidar group's share found now beside it.
"""

import json

import numpy as np
from absl import app, flags

from e2e_percep_jax import checkpoint, launch, metrics
from e2e_percep_jax import config as config_lib

flags.DEFINE_string("workdir", None, "a training run (or, with --detector, a single-frame detector's run)")
flags.DEFINE_bool("detector", False, "the run is the single-frame detector baseline's")
flags.DEFINE_integer("drives", 40, "detection drives recorded (those holding the most remembered boxes)")
FLAGS = flags.FLAGS
WINDOW_FRAMES = 30  # metrics.GROUPS' remembered window: 3 s at 10 Hz
IOU = 0.1


def found_per_vehicle(frames, score_threshold: float):
    """One recorded drive (``evaluate.RecordedFrame`` list) -> (found [T, G] bool: a detection at the
    operating score matched the vehicle at IoU 0.1; group [T, G] int; valid [T, G] bool), per vehicle slot."""
    found = np.zeros((len(frames), len(frames[0].boxes_valid)), bool)
    for t, f in enumerate(frames):
        slots = np.nonzero(f.boxes_valid)[0]
        keep = f.scores >= score_threshold
        matched = metrics.match_detections(f.boxes[keep], f.scores[keep], f.true_boxes[slots], (IOU,))[0]
        found[t, slots[matched[matched >= 0]]] = True
    group = np.stack([f.boxes_group for f in frames])
    valid = np.stack([f.boxes_valid for f in frames])
    return found, group, valid


def ceiling(recorded, score_threshold: float) -> dict:
    """The counts of the module docstring over recorded drives."""
    remembered, lidar = metrics.GROUPS.index("remembered"), metrics.GROUPS.index("lidar")
    counts = dict(
        remembered=0, remembered_found_before=0, remembered_found_now=0, remembered_kept=0, lidar=0, lidar_found_now=0
    )
    for frames in recorded:
        found, group, valid = found_per_vehicle(frames, score_threshold)
        for t, g in zip(*np.nonzero(valid & (group == remembered))):
            counts["remembered"] += 1
            before = bool(found[max(0, t - WINDOW_FRAMES) : t, g].any())
            counts["remembered_found_before"] += before
            counts["remembered_found_now"] += bool(found[t, g])
            counts["remembered_kept"] += before and bool(found[t, g])
        is_lidar = valid & (group == lidar)
        counts["lidar"] += int(is_lidar.sum())
        counts["lidar_found_now"] += int((is_lidar & found).sum())
    share = lambda k, n: counts[k] / max(counts[n], 1)
    return dict(
        counts,
        share_remembered_found_before=share("remembered_found_before", "remembered"),
        share_remembered_found_now=share("remembered_found_now", "remembered"),
        share_found_before_kept=share("remembered_kept", "remembered_found_before"),
        share_lidar_found_now=share("lidar_found_now", "lidar"),
    )


def main(argv):
    cfg = launch.run_config(argv, FLAGS.workdir)
    if FLAGS.drives < 1:
        raise app.UsageError(f"--drives={FLAGS.drives}: must be >= 1")
    # Imported once the flags are valid (a bad flag exits before the ~3 s of imports).
    from e2e_percep_jax import api, baselines
    from e2e_percep_jax import evaluate as eval_lib

    cfg = config_lib.replace(cfg, eval=dict(detection_drives=FLAGS.drives))
    if FLAGS.detector:
        _, params, _ = checkpoint.restore_params(FLAGS.workdir, cfg, None, baselines.OBJECTIVES["detection"])
        perceiver = baselines.SingleFramePerceiver(cfg, "detection")
    else:
        _, params, _ = checkpoint.restore_params(FLAGS.workdir, cfg)
        perceiver = api.run_perceiver(cfg, FLAGS.workdir)
    recorded = eval_lib.record_detections(cfg, params, perceiver, log=lambda s: print(s, flush=True))
    result = dict(workdir=FLAGS.workdir, drives=FLAGS.drives, frames=cfg.eval.detection_frames)
    print(json.dumps(dict(result, **ceiling(recorded, cfg.eval.score_threshold)), indent=1))


if __name__ == "__main__":
    flags.mark_flag_as_required("workdir")
    app.run(main, flags_parser=config_lib.parse_flags)
