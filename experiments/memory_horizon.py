"""How long a trained latent keeps the vehicles it found once every sensor is hidden from its filter.

    python experiments/memory_horizon.py --workdir=runs/cpu-bev [--drives=64 --seen=20 --hidden=30 --choose_from=0]

The occluded groups of the evaluation need a vehicle that a sensor lost while the filter saw the rest of the
frame, which few drives hold. This asks the question underneath on any drive: ``--drives`` worlds of the
run's town (reset keys from ``--seed``, held out from training's; the config's warm-up), driven for
``--seen`` + ``--hidden`` frames. The filter runs twice over the same frames (posterior means, one scan):
once seeing every frame, once seeing the first ``--seen`` only, its posterior then its prior
(``model.filter_sequence``'s ``observed``; the ego-motion head of the bird-eye grid still reads each frame's
features, so the grid is warped by the motion as it is when a vehicle is occluded). Followed: every vehicle
the lidar sees in the last seen frame and the decoder finds there (a detection at the operating score,
``eval.score_threshold``, matched at ``metrics.FOUND_IOU``, 0.1). For each k = 1..``--hidden`` frames later,
of the followed vehicles still in view: the share found with the sensors hidden (memory) and with them on
(sight), standing vehicles (moved under 0.5 m in the town since the last seen frame) and moving ones apart,
each with a 95 % bootstrap interval over drives. Beside them, chance: the same vehicles matched by the hidden run's
detections of another drive at the same frame (drive d + 1's for drive d), which is what a decoder that knew
only where vehicles usually stand would find. Prints a table and writes JSON to ``--out`` (default
``<workdir>/memory_horizon.json``).

Beside it, where the seeing run loses a vehicle: the followed vehicles that the world itself hides in the
frames after (in view, seen by neither sensor, while the filter sees the rest of the frame), pooled over
k. For the bird-eye grid, two more decodings of those frames tell the grid from z: the seeing run's z with
the hidden run's grid (``grid_kept``), and the hidden run's z with the seeing run's grid (``z_kept``). If
``grid_kept`` finds what ``sight`` loses, the grid's posterior is what erases an occluded car. Random drives
hold few such box-frames: ``--choose_from=M`` drives the sensors alone over M reset keys and keeps the
``--drives`` that hold the most (``metrics.hidden_by_the_world``), as the evaluation chooses its detection drives.

The run's detection decoder must read the latent (``--model.detection_input`` latent or grid): one that reads
the frame's features (``latent_and_features``) would see through the hiding.
"""

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

from e2e_percep_jax import checkpoint, detection, launch, metrics
from e2e_percep_jax import config as config_lib
from e2e_percep_jax import model as model_lib
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import rollout, world
from e2e_percep_jax.sim import town as town_lib

flags.DEFINE_string("workdir", None, "a training run")
flags.DEFINE_integer("seed", 7000, "the worlds' reset keys")
flags.DEFINE_integer("drives", 64, "drives (worlds)")
flags.DEFINE_integer("seen", 20, "frames the filter sees first")
flags.DEFINE_integer("hidden", 30, "frames hidden from it after them")
flags.DEFINE_integer("choose_from", 0, "choose the drives among this many for the world's occlusions (0: no)")
flags.DEFINE_string("out", None, "the JSON written (default: <workdir>/memory_horizon.json)")
FLAGS = flags.FLAGS

STANDING_M = 0.5  # a followed vehicle that moved less than this in the town is standing
DRIVES_AT_ONCE = 16  # drives filtered and decoded together (bounds the PIXOR maps' memory)
REPORTED_K = (1, 2, 3, 5, 10, 15, 20, 30)  # the table's rows (frames since the last seen one)
RUNS = ("memory", "sight", "chance")
HYBRIDS = ("grid_kept", "z_kept")  # the grid's decodings with one part from each run (the module's docstring)


def main(argv):
    cfg = launch.run_config(argv, FLAGS.workdir)
    if cfg.model.detection_input == "latent_and_features":
        raise app.UsageError(
            f"--workdir={FLAGS.workdir}: its detection decoder reads the frame's features "
            f"(--model.detection_input={cfg.model.detection_input}), which would see through the hiding"
        )
    if FLAGS.drives < 1 or FLAGS.seen < 1 or FLAGS.hidden < 1:
        raise app.UsageError("--drives, --seen and --hidden must each be >= 1")
    if FLAGS.choose_from and FLAGS.choose_from < FLAGS.drives:
        raise app.UsageError(f"--choose_from={FLAGS.choose_from}: must be 0 or at least --drives={FLAGS.drives}")
    _, params, step = checkpoint.restore_params(FLAGS.workdir, cfg)
    town = town_lib.build_town(cfg.world.town_seed)
    frames_per_drive, last_seen = FLAGS.seen + FLAGS.hidden, FLAGS.seen - 1
    ev = cfg.eval  # how candidates become boxes: the evaluation's top_k, floor and NMS

    @jax.jit
    def record(key):
        state = rollout.advance(world.reset(key, town, cfg.world), town, cfg.data.warmup_steps)
        return rollout.drive(state, town, frames_per_drive, cfg.data.image_size)[1]

    filtered_by = jax.jit(
        lambda camera, lidar, action, observed: model_lib.filter_sequence(
            params, camera, lidar, action, None, cfg, observed=observed
        )
    )

    @jax.jit
    def candidates(filtered):
        out = model_lib.decode(params, filtered, cfg)
        return detection.candidates(out["det_cls"], out["det_reg"], ev.top_k, ev.score_floor)[:2]

    keys = jax.random.split(jax.random.PRNGKey(FLAGS.seed), FLAGS.choose_from or FLAGS.drives)
    if FLAGS.choose_from:
        sees = lambda f: (f.boxes_lidar_visible, f.boxes_camera_visible, f.boxes_valid)
        counts = np.concatenate(
            [
                metrics.hidden_by_the_world(
                    *jax.device_get(sees(jax.vmap(record)(keys[i : i + DRIVES_AT_ONCE]))), last_seen
                )
                for i in range(0, FLAGS.choose_from, DRIVES_AT_ONCE)
            ]
        )
        keys = keys[np.sort(np.argsort(-counts, kind="stable")[: FLAGS.drives])]
    runs = ("memory", "sight") + (HYBRIDS if cfg.model.latent == "bev" else ())
    detections = {run: [] for run in runs}  # per run, drive and frame from the last seen: (boxes, scores)
    truth = []
    for first in range(0, FLAGS.drives, DRIVES_AT_ONCE):
        frames = jax.vmap(record)(keys[first : first + DRIVES_AT_ONCE])
        d = frames.camera.shape[0]
        seen_first = jnp.broadcast_to(jnp.arange(frames_per_drive) <= last_seen, (d, frames_per_drive))
        truth.append(
            jax.tree.map(
                np.asarray,
                (
                    frames.boxes,
                    frames.boxes_valid,
                    frames.pose,
                    frames.boxes_lidar_visible | frames.boxes_camera_visible,
                    frames.boxes_lidar_visible,
                ),
            )
        )
        filtered = {
            "memory": filtered_by(frames.camera, frames.lidar, frames.action, seen_first),
            "sight": filtered_by(frames.camera, frames.lidar, frames.action, None),
        }
        if "grid_kept" in runs:
            filtered["grid_kept"] = dict(filtered["sight"], grid=filtered["memory"]["grid"])
            filtered["z_kept"] = dict(filtered["memory"], grid=filtered["sight"]["grid"])
        for run in runs:
            cand_boxes, cand_scores = jax.device_get(candidates(filtered[run]))
            for i in range(d):
                detections[run].append([])
                for t in range(last_seen, frames_per_drive):
                    boxes, scores = detection.frame_detections(
                        cand_boxes[i, t], cand_scores[i, t], ev.score_floor, ev.nms_iou, ev.nms_merge_iou
                    )
                    keep = scores >= cfg.eval.score_threshold
                    detections[run][-1].append((boxes[keep], scores[keep]))
    boxes, valid, pose, seen_now, lidar_visible = (np.concatenate(x) for x in zip(*truth))

    def found_by(dets, drive_of):  # bool [D, frames from the last seen, N]: drive_of(d)'s detections on d
        return np.array(
            [
                [
                    metrics.matched_scores(
                        *dets[drive_of(i)][k], boxes[i, last_seen + k], valid[i, last_seen + k], metrics.FOUND_IOU
                    )
                    > -np.inf
                    for k in range(len(dets[i]))
                ]
                for i in range(len(dets))
            ]
        )

    found = {run: found_by(dets, lambda i: i) for run, dets in detections.items()}
    found["chance"] = found_by(detections["memory"], lambda i: (i + 1) % len(boxes))
    # the hidden run equals the seen one up to the last seen frame: followed are the vehicles found there
    followed = valid[:, last_seen] & lidar_visible[:, last_seen] & found["memory"][:, 0]
    town_xy = geo.ego_to_town(boxes[..., :2], pose[..., None, :2], geo.pose_yaw(pose)[..., None])
    moved = np.linalg.norm(town_xy[:, last_seen + 1 :] - town_xy[:, last_seen, None], axis=-1)
    after = slice(last_seen + 1, None)
    result = metrics.kept_shares(
        {run: found[run][:, 1:] for run in RUNS}, valid[:, after], followed, moved < STANDING_M
    )
    # the world's occlusions, box-frames pooled over k: [D, K, N] -> [D, 1, K N] (k-major, as np.tile repeats)
    pooled = lambda x: x.reshape(len(x), 1, -1)
    hidden_by_world = metrics.kept_shares(
        {run: pooled(found[run][:, 1:]) for run in runs},
        pooled(valid[:, after] & ~seen_now[:, after]),
        np.tile(followed, (1, frames_per_drive - FLAGS.seen)),
        pooled(moved < STANDING_M),
    )
    result = dict(
        workdir=os.path.abspath(FLAGS.workdir),
        checkpoint_step=step,
        latent=cfg.model.latent,
        drives=FLAGS.drives,
        seen=FLAGS.seen,
        hidden=FLAGS.hidden,
        seed=FLAGS.seed,
        choose_from=FLAGS.choose_from,
        followed=int(followed.sum()),
        score_threshold=cfg.eval.score_threshold,
        match_iou=metrics.FOUND_IOU,
        **result,
        hidden_by_the_world=hidden_by_world,
    )
    out = FLAGS.out or os.path.join(FLAGS.workdir, "memory_horizon.json")
    with open(out, "w") as f:
        json.dump(result, f, indent=1)
    print(f"{FLAGS.workdir} (step {step}, {cfg.model.latent} latent): {result['followed']} vehicles followed")
    print("| frames hidden | standing: boxes, memory %, sight %, chance % | moving: the same |")
    print("|---|---|---|")
    pct = lambda v: f"{100 * v:.1f}"
    for k in REPORTED_K:
        if k <= FLAGS.hidden:
            s, m = result["standing"], result["moving"]
            cells = [", ".join([str(e["boxes"][k - 1])] + [pct(e[run][k - 1]) for run in RUNS]) for e in (s, m)]
            print(f"| {k} | " + " | ".join(cells) + " |")
    print("followed vehicles the world hides while the filter sees (box-frames pooled over k):")
    print("| vehicles | box-frames | " + " | ".join(f"{run} %" for run in runs) + " |")
    print("|---|---|" + "---|" * len(runs))
    for name in ("standing", "moving", "all"):
        e = hidden_by_world[name]
        print(f"| {name} | {e['boxes'][0]} | " + " | ".join(pct(e[run][0]) for run in runs) + " |")
    print(f"wrote {out}")


if __name__ == "__main__":
    flags.mark_flag_as_required("workdir")
    app.run(main, flags_parser=config_lib.parse_flags)
