"""Pictures of vehicles passing out of both sensors' sight, and whether a trained run keeps them.

    python experiments/occlusion_strip.py --workdir=runs/cpu-bev [--drives=16 --min_hidden=10 --behind=town
        --out=...]

Drives the run's detection drives (the evaluation's, chosen for their remembered boxes; the busiest first) one
at a time, as the evaluation drives them, and finds the occlusions (``metrics.occlusions``): a vehicle the
lidar saw, then seen by neither sensor for at least ``--min_hidden`` frames, which the decoder had found (a
detection at the operating score, ``eval.score_threshold``, matched at ``metrics.FOUND_IOU``, 0.1) in the last
frame the lidar saw it. ``--behind`` keeps only those whose first hidden frame has the lidar's line of sight
to the vehicle's centre crossing another vehicle (``vehicle``) or a building, tree or other fixture of the
town (``town``) first (``sensors.sight_blocker``). Of those, it draws two strips
(``pictures.occlusion_strip``): the one found in the largest share of its hidden frames (the longest of
those), and the one found in the smallest share (the longest of those). It stops once it holds one found in
every hidden frame and one found in none, or after ``--drives`` drives. Writes ``--out`` (default
``<workdir>/eval/occlusion.png``) and prints every occlusion it saw, with what hid it.
"""

import os
import sys

import cv2
import numpy as np
from absl import app, flags

from e2e_percep_jax import config as config_lib
from e2e_percep_jax import launch

flags.DEFINE_string("workdir", None, "a training run")
flags.DEFINE_integer("drives", 16, "detection drives searched at most, the busiest first")
flags.DEFINE_integer("min_hidden", 10, "frames a vehicle stays hidden from both sensors, at least")
flags.DEFINE_enum("behind", "any", ["any", "vehicle", "town"], "what first hides the vehicle's centre")
flags.DEFINE_string("out", None, "the PNG written (default: <workdir>/eval/occlusion.png)")
FLAGS = flags.FLAGS


def main(argv):
    try:
        launch.prepare(argv)
        cfg = config_lib.validate(config_lib.run_config(FLAGS.workdir))
        if FLAGS.drives < 1 or FLAGS.min_hidden < 1:
            raise ValueError(f"--drives={FLAGS.drives} and --min_hidden={FLAGS.min_hidden} must each be >= 1")
        if cfg.eval.detection_drives < 1:
            raise ValueError(f"--workdir={FLAGS.workdir}: its evaluation has no detection drives to search")
        # Imported once the flags are valid: a bad flag exits in a fraction of a second.
        from e2e_percep_jax import checkpoint, metrics, pictures
        from e2e_percep_jax import evaluate as eval_lib
        from e2e_percep_jax.sim import geometry as geo
        from e2e_percep_jax.sim import sensors
        from e2e_percep_jax.sim import town as town_lib

        cfg, params, step = checkpoint.restore_params(FLAGS.workdir, cfg)
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"error: {e}")
    threshold = cfg.eval.score_threshold
    perceiver = eval_lib.default_perceiver(cfg, FLAGS.workdir)
    town = town_lib.build_town(cfg.eval.town_seed)

    def hidden_by(frame, slot):  # what the lidar's sight line crosses first: "vehicle", a fixture's kind, or None
        pose = np.asarray(frame["pose"], np.float64)
        buildings = geo.box_to_ego(np.asarray(town.building_box, np.float64), pose[:2], geo.pose_yaw(pose))
        kind, i = sensors.sight_blocker(frame["boxes"][slot], frame["boxes"], buildings)
        return town_lib.BUILDING_KIND_NAMES[town.building_kind[i]] if kind == "town" else kind

    keys, counts = eval_lib.detection_start_keys(cfg, town)
    busiest = np.argsort(-counts, kind="stable") if counts is not None else np.arange(len(keys))
    most = least = None  # (share of hidden frames found, hidden frames, drive, occlusion, frames, what hid it)
    for drive in busiest[: FLAGS.drives]:
        frames = eval_lib.record_pictured_drive(cfg, params, perceiver, keys[drive])
        stacked = {k: np.stack([f[k] for f in frames]) for k in ("boxes_valid", "boxes_group")}
        score = np.stack(
            [
                metrics.matched_scores(
                    f["pred_boxes"], f["pred_scores"], f["boxes"], f["boxes_valid"], metrics.FOUND_IOU
                )
                for f in frames
            ]
        )
        for occ in metrics.occlusions(stacked["boxes_group"], stacked["boxes_valid"], score, FLAGS.min_hidden):
            share = float(np.mean(occ.scores >= threshold))
            found_before = occ.score_before >= threshold
            behind = hidden_by(frames[occ.frame], occ.slot)
            print(
                f"drive {drive}, vehicle {occ.slot}: hidden frames {occ.frame}-{occ.frame + occ.hidden - 1} "
                f"behind {behind or 'nothing in plan'}, {'found' if found_before else 'not found'} before, "
                f"found in {100 * share:.0f} % of them",
                flush=True,
            )
            wanted = {"any": True, "vehicle": behind == "vehicle", "town": behind in town_lib.BUILDING_KIND_NAMES}
            if not found_before or not wanted[FLAGS.behind]:
                continue
            entry = (share, occ.hidden, drive, occ, frames, behind)
            if most is None or entry[:2] > most[:2]:
                most = entry
            if least is None or (share, -occ.hidden) < (least[0], -least[1]):
                least = entry
        if most is not None and most[0] == 1.0 and least[0] == 0.0:
            break
    if most is None:
        sys.exit(
            f"error: no occlusion of at least {FLAGS.min_hidden} frames (--behind={FLAGS.behind}) found before it in "
            f"{FLAGS.drives} drives"
        )
    rows = []
    for name, entry in (("most kept", most), ("least kept", least)):
        if name == "least kept" and entry[0] == most[0]:
            print("every occlusion was kept as often as the most kept one: one strip")
            continue
        share, hidden, drive, occ, frames, behind = entry
        strip = pictures.occlusion_strip(frames, occ, threshold)
        band = np.zeros((20, strip.shape[1], 3), np.uint8)
        pictures.title(
            band,
            f"{name}: detection drive {drive}, vehicle {occ.slot}, hidden from both sensors behind "
            f"{f'a {behind}' if behind else 'nothing in plan'} for {hidden} frames, found in {100 * share:.0f} % "
            "of them (white: the vehicle; cyan: decoded; orange: remembered)",
        )
        rows.append(np.concatenate([band, strip], 0))
    width = max(r.shape[1] for r in rows)
    image = np.concatenate([np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows], 0)
    out = FLAGS.out or os.path.join(FLAGS.workdir, "eval", "occlusion.png")
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    cv2.imwrite(out, cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    print(f"wrote {out} (step {step})")


if __name__ == "__main__":
    app.run(main, flags_parser=config_lib.parse_flags)
