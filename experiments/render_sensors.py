"""Pictures of the sensors for people: one panel PNG and a video of the ego driving through the town.

Both show camera | lidar | roadmap | ground-truth boxes over the BEV (green: seen by the lidar, orange:
occluded), in the reference's layout. Usage (R = 128, 100 vehicles, 200 warm-up steps):

    python experiments/render_sensors.py --config=paper --out_dir=runs/sensors

writes ``sensors_R128.png`` (the first frame) and ``sensors_R128.mp4`` (``--seconds`` of driving at 10 Hz).
"""
import os

import cv2
import jax
import numpy as np
from absl import app, flags

from e2e_percep_jax import batch, config, panels, world
from e2e_percep_jax.town import build_town

flags.DEFINE_string("out_dir", "runs/sensors", "where the PNG and MP4 go")
flags.DEFINE_integer("seed", 0, "world reset key")
flags.DEFINE_float("seconds", 20.0, "video length (simulated seconds, 10 frames per second)")
flags.DEFINE_integer("panel_px", 256, "pixels per view in the pictures")
config.define_flags()
FLAGS = flags.FLAGS


def main(argv):
    del argv
    cfg = config.from_flags()
    r = cfg.data.image_size
    town = build_town(cfg.world.town_seed)
    state = world.reset(jax.random.PRNGKey(FLAGS.seed), town, cfg.world)
    warm = jax.jit(lambda s: jax.lax.fori_loop(0, cfg.data.warmup_steps, lambda _, x: world.step(x, town), s))
    drive = jax.jit(batch.rollout, static_argnums=(2, 3))
    num_frames = int(round(FLAGS.seconds / world.DT_S))
    _, frames = drive(warm(state), town, num_frames, r)
    frames = jax.tree.map(np.asarray, frames)
    panel = lambda t: panels.frame_panel({k: v[t] for k, v in frames.items()}, FLAGS.panel_px)

    os.makedirs(FLAGS.out_dir, exist_ok=True)
    png = os.path.join(FLAGS.out_dir, f"sensors_R{r}.png")
    cv2.imwrite(png, panel(0)[..., ::-1])
    mp4 = os.path.join(FLAGS.out_dir, f"sensors_R{r}.mp4")
    first = panel(0)
    video = cv2.VideoWriter(mp4, cv2.VideoWriter_fourcc(*"mp4v"), 1.0 / world.DT_S, (first.shape[1], first.shape[0]))
    for t in range(num_frames):
        video.write(panel(t)[..., ::-1])
    video.release()
    print(f"wrote {png} and {mp4} ({num_frames} frames)")


if __name__ == "__main__":
    app.run(main)
