"""A vehicle passing behind a building, frame by frame, and whether a trained run keeps it.

    python experiments/building_occlusion.py --workdir=runs/cpu-bev [--speed_mps=2 --out=...]

The world's traffic never hides a vehicle the lidar saw behind a building inside the bird-eye view (its
buildings stand too far from the road; BUILD_NOTES, Evaluation), so this drive is built by hand
(:func:`e2e_percep_jax.sim.scene.kerb_building_drive`) in the run's evaluation town: the ego stands before a
signalised junction, one building stands on the junction's near right corner at the kerb, and one vehicle
drives straight across from the ego's left and away down the street to its right, behind that building; no
other traffic. The run's perceiver filters the drive from its first frame through the inference API
(``e2e_percep_jax.load``, ``Perceiver.step``, the belief started at the true pose), and the frames are scored
as the evaluation scores them (groups, detections at ``eval.score_floor`` after NMS at ``eval.nms_iou``, a
vehicle found at ``eval.score_threshold`` and rotated IoU ``metrics.FOUND_IOU``). Writes a strip
(``pictures.occlusion_strip``; its columns count frames from the last one in which either sensor saw the
vehicle, led by the frame it was found best and the last it was found) of the frames around the vehicle's
hidden stretch to ``--out`` (default ``<workdir>/eval/building_occlusion.png``) and prints, frame by frame,
who sees the vehicle and the score of the detection matched to it.
"""

import os
import sys

import cv2
import numpy as np
from absl import app, flags

from e2e_percep_jax import config as config_lib
from e2e_percep_jax import launch

flags.DEFINE_string("workdir", None, "a training run")
flags.DEFINE_float("speed_mps", 2.0, "the driven vehicle's speed")
flags.DEFINE_string("out", None, "the PNG written (default: <workdir>/eval/building_occlusion.png)")
FLAGS = flags.FLAGS


def main(argv):
    try:
        launch.prepare(argv)
        cfg = config_lib.validate(config_lib.run_config(FLAGS.workdir))
        if not 0.5 <= FLAGS.speed_mps <= 10.0:
            raise ValueError(f"--speed_mps={FLAGS.speed_mps}: must lie in [0.5, 10] (a vehicle crossing a junction)")
        # Imported once the flags are valid: a bad flag exits in a fraction of a second.
        import jax
        import jax.numpy as jnp

        import e2e_percep_jax as e2e
        from e2e_percep_jax import metrics, pictures
        from e2e_percep_jax.sim import rollout, scene, world
        from e2e_percep_jax.sim import town as town_lib

        perceiver, params = e2e.load(FLAGS.workdir)
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"error: {e}")
    ev = perceiver.cfg.eval
    town = town_lib.build_town(ev.town_seed)
    drive = scene.kerb_building_drive(
        town, world.reset(jax.random.PRNGKey(ev.seed), town, cfg.world), speed_mps=FLAGS.speed_mps
    )
    frames = scene.observe_drive(drive, cfg.data.image_size)
    seen = {k: np.stack([f[k] for f in frames]) for k in ("boxes_lidar_visible", "boxes_camera_visible")}
    groups = np.asarray(
        metrics.box_groups(*seen.values(), rollout.frames_since_seen({k: jnp.asarray(v) for k, v in seen.items()}))
    )
    step = jax.jit(perceiver.step)
    state = perceiver.init(1)
    start = jnp.asarray(frames[0]["pose"])[None]
    for f, frame in enumerate(frames):
        state, out = step(
            params,
            state,
            frame["camera"][None],
            frame["lidar"][None],
            jnp.zeros((1, 2), jnp.float32),  # the ego stands: no pedal, no steering
            start_pose=start,
            lidar_scan=frame["lidar_scan"][None],
        )
        decoded = perceiver.boxes(out, ev.score_floor, ev.nms_iou, ev.nms_merge_iou)
        frame["pred_boxes"], frame["pred_scores"] = decoded[0]
        frame["boxes_group"] = groups[f]
        if out.roadmap is not None:
            frame["recon_roadmap"] = np.round(255 * np.asarray(out.roadmap[0])).astype(np.uint8)
    valid = np.stack([f["boxes_valid"] for f in frames])
    score = np.stack(
        [
            metrics.matched_scores(f["pred_boxes"], f["pred_scores"], f["boxes"], f["boxes_valid"], metrics.FOUND_IOU)
            for f in frames
        ]
    )
    for f in np.nonzero(valid[:, 0])[0]:
        print(f"frame {f}: {metrics.GROUPS[groups[f, 0]]}, matched score {score[f, 0]:.2f}")
    # the stretch in which neither sensor sees the vehicle after one last did (the camera may see it last)
    hidden = valid[:, 0] & (groups[:, 0] == metrics.GROUPS.index("remembered"))
    if not hidden.any():
        sys.exit("error: the built drive holds no frame in which the vehicle is hidden after a sensor saw it")
    first = int(np.argmax(hidden))
    length = int(np.argmin(np.append(hidden[first:], False)))
    occ = metrics.Occlusion(0, first, length, float(score[first - 1, 0]), score[first : first + length, 0])
    share = float(np.mean(occ.scores >= ev.score_threshold))
    # lead with the frame the vehicle was found best and the last it was found at the operating score
    found = np.nonzero(score[: occ.frame, 0] >= ev.score_threshold)[0]
    lead = (int(np.argmax(score[: occ.frame, 0])), *found[-1:])
    strip = pictures.occlusion_strip(frames, occ, ev.score_threshold, lead=lead)
    band = np.zeros((20, strip.shape[1], 3), np.uint8)
    pictures.title(
        band,
        f"hand-built, town {ev.town_seed}, junction {drive.node}: behind a kerb building, hidden from both sensors "
        f"for {occ.hidden} frames in view, found in {100 * share:.0f} % (white: the vehicle; cyan: decoded)",
    )
    out_path = FLAGS.out or os.path.join(FLAGS.workdir, "eval", "building_occlusion.png")
    os.makedirs(os.path.dirname(os.path.abspath(out_path)), exist_ok=True)
    cv2.imwrite(out_path, cv2.cvtColor(np.concatenate([band, strip], 0), cv2.COLOR_RGB2BGR))
    found_before = "found" if occ.score_before >= ev.score_threshold else "not found"
    print(
        f"hidden frames {occ.frame}-{occ.frame + occ.hidden - 1}: {found_before} in the last frame a sensor saw it, "
        f"found in {100 * share:.0f} % of the hidden frames; wrote {out_path}"
    )


if __name__ == "__main__":
    app.run(main, flags_parser=config_lib.parse_flags)
