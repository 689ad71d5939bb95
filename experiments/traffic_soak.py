"""Long-drive soak of the traffic: does it keep moving, and do bodies stay apart and on the road?

    python experiments/traffic_soak.py --seeds=7,8,9 --num_steps=1000000 --out=runs/soak
    python experiments/traffic_soak.py --config=cpu --eval_drives --num_steps=2100 --out=runs/soak_eval

Drives one world per seed (``PRNGKey(seed)``, the config's town and vehicle count), or with
``--eval_drives`` the evaluation's own E start worlds (``--eval.*``), for ``--num_steps`` steps and
measures, for every 10 s window (100 steps):

- the share of vehicles (ego included) that moved at all (speed > 0.1 m/s at some step);
- overlapping bodies: every pair whose bounding circles meet is tested exactly (separating axes) at
  every step; a vehicle with more than ``_NEIGHBOURS`` such neighbours is counted as unchecked;
- corners off the drivable area, read from the town's semantic raster at every step;
- the longest any vehicle has stood (``veh_standing_steps``): below ``world.REROUTE_AFTER_S`` nobody has
  re-routed.

Writes ``<out>/soak.json`` (per-window arrays and a summary) and ``<out>/soak.png`` (moving share over
time, one line per seed) and prints the summary.
"""

import functools
import json
import os
import sys
import time

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

from e2e_percep_jax import config as config_lib
from e2e_percep_jax import evaluate
from e2e_percep_jax.sim import geometry, world
from e2e_percep_jax.sim import town as town_lib

config_lib.define_flags()
flags.DEFINE_list("seeds", ["7", "8", "9"], "reset keys, one world each")
flags.DEFINE_boolean("eval_drives", False, "drive the evaluation's start worlds instead of --seeds")
flags.DEFINE_integer("num_steps", 1_000_000, "world steps per drive (a multiple of 100)")
flags.DEFINE_string("out", None, "output directory")
FLAGS = flags.FLAGS

WINDOW_STEPS = 100  # 10 s
MOVING_MPS = 0.1
_NEIGHBOURS = 6  # nearest vehicles per vehicle whose bodies are tested against it
_WINDOWS_PER_CALL = 500
_DRIVABLE = np.array([town_lib.SEM_ROAD, town_lib.SEM_LANE_WHITE, town_lib.SEM_CENTRE_YELLOW, town_lib.SEM_STOP_LINE])


def _body_checks(state, town):
    """(overlapping pairs, unchecked vehicles, corners off the drivable area) of one world now."""
    box = state.veh_box  # [N+1, 5]
    radius = 0.5 * jnp.hypot(box[:, 3], box[:, 4])
    dist = jnp.linalg.norm(box[:, None, :2] - box[None, :, :2], axis=-1)
    dist = jnp.where(jnp.eye(box.shape[0], dtype=bool), jnp.inf, dist)
    close = dist < radius[:, None] + radius[None, :]
    _, nearest = jax.lax.top_k(-dist, _NEIGHBOURS)  # [N+1, K]
    tested = jnp.take_along_axis(close, nearest, 1)
    hit = tested & geometry.boxes_overlap(box[:, None, :], box[nearest])
    unchecked = close.sum(1) > _NEIGHBOURS
    corners = geometry.box_corners(box)  # [N+1, 4, 2]
    col, row = jnp.moveaxis(jnp.floor((corners - town.map_origin_m) / town.map_res_m).astype(jnp.int32), -1, 0)
    sem = town.sem_map[row, col]
    off_road = ~jnp.isin(sem, jnp.asarray(_DRIVABLE))
    return hit.sum() // 2, unchecked.sum(), off_road.sum()


@functools.partial(jax.jit, static_argnames="num_windows")
def _windows(states, town, num_windows):
    """``num_windows`` windows of every world: (states, per-window stats [windows, worlds])."""

    def one_window(states, _):
        def body(carry, _):
            states, moved, overlaps, unchecked, off_road = carry
            states = jax.vmap(lambda s: world.step(s, town))(states)
            o, u, r = jax.vmap(lambda s: _body_checks(s, town))(states)
            return (
                states,
                moved | (states.veh_speed_mps > MOVING_MPS),
                overlaps + o,
                unchecked + u,
                off_road + r,
            ), None

        zeros = jnp.zeros(states.step.shape, jnp.int32)
        moved = jnp.zeros(states.veh_speed_mps.shape, bool)
        (states, moved, overlaps, unchecked, off_road), _ = jax.lax.scan(
            body, (states, moved, zeros, zeros, zeros), None, length=WINDOW_STEPS
        )
        return states, dict(
            moving_share=moved.mean(-1),
            overlaps=overlaps,
            unchecked=unchecked,
            off_road=off_road,
            longest_standing=states.veh_standing_steps.max(-1),
        )

    return jax.lax.scan(one_window, states, None, length=num_windows)


def _plot(moving_share, labels, path):
    """Moving share [windows, worlds] against time, one coloured line per world, on a white canvas."""
    height, width, margin = 360, 1000, 40
    canvas = np.full((height, width, 3), 255, np.uint8)
    x = lambda i: margin + int(i * (width - 2 * margin) / max(len(moving_share) - 1, 1))
    y = lambda share: height - margin - int(share * (height - 2 * margin))
    for share in (0.0, 0.5, 1.0):
        cv2.line(canvas, (margin, y(share)), (width - margin, y(share)), (220, 220, 220), 1)
        cv2.putText(canvas, f"{share:.1f}", (4, y(share) + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    colours = [(200, 60, 40), (40, 140, 40), (40, 60, 200), (150, 60, 160), (30, 150, 190)]
    # One point per ``stride`` windows (the minimum over them), so a short stall still shows.
    stride = max(len(moving_share) // (width - 2 * margin), 1)
    lows = moving_share[: len(moving_share) // stride * stride].reshape(-1, stride, moving_share.shape[1]).min(1)
    for w, label in enumerate(labels):
        points = np.array([[x(i * stride), y(v)] for i, v in enumerate(lows[:, w])], np.int32)
        cv2.polylines(canvas, [points], False, colours[w % len(colours)], 1, cv2.LINE_AA)
        cv2.putText(
            canvas, label, (width - 130, 20 + 16 * w), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colours[w % len(colours)], 1
        )
    hours = len(moving_share) * WINDOW_STEPS * world.DT_S / 3600
    cv2.putText(
        canvas,
        f"share of vehicles moving per 10 s window (min per {stride} windows), {hours:.1f} h of driving",
        (margin, 20),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.45,
        (0, 0, 0),
        1,
    )
    cv2.imwrite(path, canvas)


def main(argv):
    try:
        config_lib.check_launch(argv, required=("out",))
        cfg = config_lib.from_flags()
        seeds = [int(s) for s in FLAGS.seeds]
        if any(s < 0 for s in seeds):
            raise ValueError(f"--seeds={FLAGS.seeds}: must be >= 0")
        if FLAGS.num_steps < WINDOW_STEPS or FLAGS.num_steps % WINDOW_STEPS:
            raise ValueError(f"--num_steps={FLAGS.num_steps}: must be a positive multiple of {WINDOW_STEPS}")
        town_seed = cfg.eval.town_seed if FLAGS.eval_drives else cfg.world.town_seed
        world.check_vehicle_count(cfg.world, town_seed)
    except ValueError as e:
        sys.exit(f"error: {e}")
    os.makedirs(FLAGS.out, exist_ok=True)
    town = town_lib.build_town(town_seed)
    if FLAGS.eval_drives:
        keys = evaluate.start_keys(cfg)
        labels = [f"eval drive {i}" for i in range(len(keys))]
    else:
        keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
        labels = [f"seed {s}" for s in seeds]
    states = jax.vmap(lambda k: world.reset(k, town, cfg.world))(keys)
    stats, start, done = [], time.time(), 0
    while done < FLAGS.num_steps:
        num_windows = min(_WINDOWS_PER_CALL, (FLAGS.num_steps - done) // WINDOW_STEPS)
        states, chunk = _windows(states, town, num_windows)
        stats.append(jax.tree.map(np.asarray, chunk))
        done += num_windows * WINDOW_STEPS
        print(
            f"{done:,} steps  min moving share so far {min(s['moving_share'].min() for s in stats):.2f}  "
            f"{done * len(labels) / (time.time() - start):,.0f} world steps/s",
            flush=True,
        )
    stats = {k: np.concatenate([s[k] for s in stats]) for k in stats[0]}  # [windows, worlds]
    summary = dict(
        worlds=labels,
        town_seed=town_seed,
        num_vehicles=cfg.world.num_vehicles,
        num_steps=FLAGS.num_steps,
        window_steps=WINDOW_STEPS,
        min_moving_share=stats["moving_share"].min(0).round(3).tolist(),
        first_window_below_half=[
            int(np.argmax(col < 0.5)) if (col < 0.5).any() else None for col in stats["moving_share"].T
        ],
        overlaps=stats["overlaps"].sum(0).tolist(),
        unchecked=stats["unchecked"].sum(0).tolist(),
        off_road_corners=stats["off_road"].sum(0).tolist(),
        longest_standing_steps=stats["longest_standing"].max(0).tolist(),
        reroute_after_steps=int(world.REROUTE_AFTER_S / world.DT_S),
        windows_past_reroute_time=(stats["longest_standing"] >= int(world.REROUTE_AFTER_S / world.DT_S))
        .sum(0)
        .tolist(),
    )
    with open(os.path.join(FLAGS.out, "soak.json"), "w") as f:
        json.dump(dict(summary=summary, moving_share=stats["moving_share"].round(3).T.tolist()), f)
    _plot(stats["moving_share"], labels, os.path.join(FLAGS.out, "soak.png"))
    print(json.dumps(summary))


if __name__ == "__main__":
    app.run(main, flags_parser=config_lib.parse_flags)
