"""Training curves a person can watch: TensorBoard event files beside a run's ``metrics.jsonl``.

    tensorboard --logdir runs/        # every run under runs/, side by side

The writer is tensorboardX's ``FileWriter``, an optional extra (``pip install -e '.[tensorboard]'``): a
small pure-Python package (protobuf and numpy, which the project already pulls) that writes event files
without TensorFlow or PyTorch. Images are PNG-encoded by OpenCV here (tensorboardX's own image helper
would pull Pillow). Without tensorboardX training runs as before and says once that it writes no events.

:class:`Board` writes every ``metrics.jsonl`` record as scalars (each loss term, the gradient norm,
steps/s, the non-finite counters) plus the learning rate, and at every checkpoint of a single-process run
:func:`preview` images
of one training sequence's last frame: each input beside its reconstruction, and the pose belief's place
probabilities with the true cell marked. A resumed run purges the events past its checkpoint, as
``metrics.jsonl`` is truncated there.
"""

import functools

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax import model as model_lib
from e2e_percep_jax import pose_belief
from e2e_percep_jax.config import Config

NOT_LOSSES = ("grad_norm", "steps_per_s", "nonfinite_in_a_row", "nonfinite_total")  # record fields; the rest
# (but "step") are loss terms, filed under loss/


class Board:
    """A TensorBoard writer for run ``workdir`` from step ``start_step`` on; a no-op without tensorboardX or
    without a ``workdir`` (the processes of a multi-process run but the first)."""

    def __init__(self, workdir: str | None, start_step: int, log=print):
        self.writer = None
        if workdir is None:
            return
        try:
            from tensorboardX import FileWriter
            from tensorboardX.proto.event_pb2 import Event, SessionLog
            from tensorboardX.proto.summary_pb2 import Summary
        except ImportError:
            log("tensorboardX is not installed: no TensorBoard events (pip install -e '.[tensorboard]')")
            return
        self.summary = Summary
        # An event file is named by the second it opened in (and the host), and opening truncates: a resume
        # within the same second as the run before it would erase that run's events, so the name also
        # carries the step it starts from.
        self.writer = FileWriter(workdir, flush_secs=30, filename_suffix=f".from_step{start_step}")
        if start_step:  # TensorBoard drops the events at or past a START's step: those written after the checkpoint
            self.writer.add_event(Event(step=start_step, session_log=SessionLog(status=SessionLog.START)))

    def scalars(self, record: dict, learning_rate: float) -> None:
        if self.writer is None:
            return
        values = [
            self.summary.Value(tag=name if name in NOT_LOSSES else f"loss/{name}", simple_value=value)
            for name, value in record.items()
            if name != "step"
        ]
        values.append(self.summary.Value(tag="learning_rate", simple_value=learning_rate))
        self.writer.add_summary(self.summary(value=values), record["step"])

    def images(self, step: int, images: dict) -> None:
        """``images``: name -> uint8 [H, W, 3]."""
        if self.writer is None:
            return
        values = []
        for name, image in images.items():
            image = np.asarray(image)
            png = cv2.imencode(".png", image[..., ::-1])[1].tobytes()  # (OpenCV writes BGR)
            values.append(
                self.summary.Value(
                    tag=name,
                    image=self.summary.Image(
                        height=image.shape[0], width=image.shape[1], colorspace=3, encoded_image_string=png
                    ),
                )
            )
        self.writer.add_summary(self.summary(value=values), step)
        self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


def _heat(p, true_index, n: int):
    """Place probabilities [G] as a uint8 [n, n, 3] image, north up, scaled to their maximum, the true
    cell in green."""
    grey = (255.0 * p / jnp.maximum(p.max(), 1e-30)).reshape(n, n)
    image = jnp.stack([grey, grey, grey], -1)
    image = image.reshape(n * n, 3).at[true_index].set(jnp.array([0.0, 255.0, 0.0])).reshape(n, n, 3)
    return image[::-1].astype(jnp.uint8)  # row i runs along y: flipped, north is up


@functools.partial(jax.jit, static_argnames="cfg")
def preview(params, camera, lidar, roadmap, action, pose, cfg: Config) -> dict:
    """Images of the first sequence's last frame (inputs [B, T+1, ...] as a batch holds them): for each
    image the variant reconstructs, the input beside the reconstruction (uint8 [R, 2R, 3]); with the
    belief head, ``pose_belief``: its place probabilities (uint8 [n, n, 3], the true cell green)."""
    out = model_lib.filter_sequence(params, camera[:1], lidar[:1], action[:1], None, cfg)
    last = jax.tree.map(lambda x: x[:, -1], out)
    decoded = model_lib.decode(params, last, cfg)
    inputs = {"camera": camera, "lidar": lidar, "roadmap": roadmap}
    to_uint8 = lambda x: (jnp.clip(x, 0.0, 1.0) * 255.0 + 0.5).astype(jnp.uint8)
    images = {
        f"reconstruction/{name}": jnp.concatenate([inputs[name][0, -1], to_uint8(decoded[name][0])], 1)
        for name in model_lib.reconstructed_images(cfg.model.variant)
    }
    if cfg.model.pose_head == "belief":
        grid = pose_belief.grid_of(cfg.model)
        head = model_lib.pose_belief_head(params, last, cfg)
        cell, _ = pose_belief.true_cell(pose[0, -1, :2], grid)
        images["pose_belief"] = _heat(jax.nn.softmax(head["place_logit"][0]), cell, grid.n)
    return images
