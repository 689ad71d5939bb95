"""Pictures of the world for people: the whole town from above, its traffic, and the ego's sensors.

Usage (the demo config: R = 64, 100 vehicles, 200 warm-up steps; about a minute on 2 CPU cores):

    python experiments/render_world.py --out_dir=runs/world

writes to ``--out_dir``:

- ``town.png``: the whole town, north up, after warm-up: lanes (thin blue centre lines), lights in their
  current state (red / yellow / green dots at the stop lines), buildings and landmarks in their colours,
  vehicles (black outline, a tick towards the front; the ego outlined in magenta);
- ``traffic.mp4``: the same view while the traffic drives for ``--seconds`` (10 frames per second);
- ``sensors_R<R>.png``: camera | lidar | roadmap | ground-truth boxes (coloured by who saw them: green the
  lidar, yellow the camera only, orange remembered, grey unseen), in the reference's layout, of the video's frame where the lidar sees the most vehicles;
- ``sensors_R<R>.mp4``: those four views while the ego drives, frame for frame with ``traffic.mp4``.
"""

import os

import cv2
import jax
import numpy as np
from absl import app, flags

from e2e_percep_jax import config, pictures
from e2e_percep_jax.sim import rollout, world
from e2e_percep_jax.sim.town import build_town

flags.DEFINE_string("out_dir", "runs/world", "where the PNGs and MP4s go")
flags.DEFINE_integer("seed", 11, "world reset key (11: an ego that keeps moving through traffic in the default town)")
flags.DEFINE_float("seconds", 20.0, "video length (simulated seconds, 10 frames per second)")
flags.DEFINE_integer("panel_px", 256, "pixels per sensor view")
flags.DEFINE_float("town_px_per_m", 2.0, "scale of the top-down town pictures")
config.define_flags()
flags.FLAGS.set_default("config", "demo")
FLAGS = flags.FLAGS


def write_video(path, images):
    """Writes RGB images [H, W, 3] (any iterable, drawn as it goes) as an MP4 at 1 / DT_S frames per second."""
    video = None
    for image in images:
        if video is None:
            video = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"mp4v"), 1.0 / world.DT_S, image.shape[1::-1])
        video.write(np.ascontiguousarray(image[..., ::-1]))
    video.release()


def main(argv):
    del argv
    cfg = config.from_flags()
    r = cfg.data.image_size
    num_frames = int(round(FLAGS.seconds / world.DT_S))
    town = build_town(cfg.world.town_seed)
    state = world.reset(jax.random.PRNGKey(FLAGS.seed), town, cfg.world)
    # (The town goes in as an argument, not a closed-over constant: that compiles faster.)
    state = jax.jit(rollout.advance, static_argnums=2)(state, town, cfg.data.warmup_steps)
    # Whole states for the top-down views, frames for the sensors.
    _, frames, states = jax.jit(rollout.drive, static_argnums=(2, 3, 4))(state, town, num_frames, r, True)
    states, frames = jax.tree.map(np.asarray, (states, frames))
    at = lambda tree, t: jax.tree.map(lambda a: a[t], tree)

    os.makedirs(FLAGS.out_dir, exist_ok=True)
    out = lambda name: os.path.join(FLAGS.out_dir, name)
    view = pictures.TopDown(town, px_per_m=FLAGS.town_px_per_m, draw_lanes=True)
    cv2.imwrite(out("town.png"), view.draw(at(states, 0))[..., ::-1])
    write_video(out("traffic.mp4"), (view.draw(at(states, t)) for t in range(num_frames)))
    panel = lambda t: pictures.frame_panel(at(frames, t), FLAGS.panel_px)
    seen = (frames["boxes_valid"] & frames["boxes_lidar_visible"]).sum(-1)  # [T] vehicles the lidar sees
    cv2.imwrite(out(f"sensors_R{r}.png"), panel(int(np.argmax(seen)))[..., ::-1])
    write_video(out(f"sensors_R{r}.mp4"), (panel(t) for t in range(num_frames)))
    print(f"wrote town.png, traffic.mp4, sensors_R{r}.png, sensors_R{r}.mp4 ({num_frames} frames) to {FLAGS.out_dir}")


if __name__ == "__main__":
    app.run(main)
