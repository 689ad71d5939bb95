"""TensorBoard events of a training run (e2e_percep_jax/board.py), read back with a TFRecord reader written
here: the scalars are metrics.jsonl's records, the images are the inputs beside their reconstructions and
the pose belief; without tensorboardX the run trains as before."""

import glob
import struct
import sys
import time

import cv2
import numpy as np
import pytest
from helpers import TINY, read_jsonl, synthetic_batch, tiny

from e2e_percep_jax import board as board_lib
from e2e_percep_jax import pose_belief, train

pytest.importorskip("tensorboardX")
from tensorboardX.proto import event_pb2  # noqa: E402 (after the skip)

CFG = tiny(num_steps=4, checkpoint_every=2, log_every=1)


def batches(start, stop=CFG.train.num_steps):
    for step in range(start, stop):
        yield step, synthetic_batch(step, TINY)


def read_events(workdir):
    """Every event in the run's event files: the TFRecord framing (length, its CRC, data, its CRC) taken
    apart by hand, each record an Event protocol buffer."""
    events = []
    for path in sorted(glob.glob(f"{workdir}/events.out.tfevents.*")):
        data = open(path, "rb").read()
        at = 0
        while at < len(data):
            (length,) = struct.unpack("<Q", data[at : at + 8])
            events.append(event_pb2.Event.FromString(data[at + 12 : at + 12 + length]))
            at += 12 + length + 4
    return events


def board_contents(workdir):
    """(tag -> step -> scalar, (tag, step) -> decoded RGB image, the steps of the resume markers)."""
    scalars, images, starts = {}, {}, []
    for event in read_events(workdir):
        if event.HasField("session_log"):
            starts.append(event.step)
        for value in event.summary.value:
            if value.HasField("image"):
                png = np.frombuffer(value.image.encoded_image_string, np.uint8)
                images[(value.tag, event.step)] = cv2.imdecode(png, cv2.IMREAD_COLOR)[..., ::-1]  # (BGR decoded)
            else:
                scalars.setdefault(value.tag, {})[event.step] = value.simple_value
    return scalars, images, starts


def test_a_resume_in_the_same_second_keeps_the_events_before_it(tmp_path, monkeypatch):
    """Event files are named by the second they open in; a run resumed within that second (a fast machine, a
    crash and restart) still keeps the first run's events."""
    monkeypatch.setattr(time, "time", lambda: 1_800_000_000.0)
    for start, step in ((0, 1), (1, 2)):
        board = board_lib.Board(str(tmp_path), start_step=start, log=pytest.fail)
        board.scalars({"step": step, "kl": float(step)}, learning_rate=1e-3)
        board.close()
    scalars, _, starts = board_contents(tmp_path)
    assert scalars["loss/kl"] == {1: 1.0, 2: 2.0} and starts == [1]


def test_the_board_files_scalars_and_images_after_a_resume_marker_and_without_its_writer_nothing(tmp_path, monkeypatch):
    """The writer alone (the tests below train through it): a record's loss terms under loss/, the other
    fields and the learning rate by name, images losslessly, and a resumed run's START marker."""
    image = np.random.default_rng(0).integers(0, 256, (8, 16, 3), np.uint8)
    board = board_lib.Board(str(tmp_path / "run"), start_step=3, log=pytest.fail)
    board.scalars({"step": 4, "kl": 1.5, "grad_norm": 2.0}, learning_rate=1e-3)
    board.images(4, {"reconstruction/camera": image})
    board.close()
    scalars, images, starts = board_contents(tmp_path / "run")
    assert starts == [3]
    assert {tag: values[4] for tag, values in scalars.items()} == pytest.approx(
        {"loss/kl": 1.5, "grad_norm": 2.0, "learning_rate": 1e-3}  # (float32 in the event)
    )
    assert all(list(values) == [4] for values in scalars.values())
    assert list(images) == [("reconstruction/camera", 4)]
    np.testing.assert_array_equal(images[("reconstruction/camera", 4)], image)

    monkeypatch.setitem(sys.modules, "tensorboardX", None)  # import tensorboardX now raises ImportError
    said = []
    bare = board_lib.Board(str(tmp_path / "bare"), start_step=0, log=said.append)
    bare.scalars({"step": 1, "kl": 1.0}, learning_rate=1e-3)
    bare.images(1, {"reconstruction/camera": image})
    bare.close()
    assert len(said) == 1 and "tensorboardX is not installed" in said[0]
    assert not (tmp_path / "bare").exists()


@pytest.mark.slow
def test_events_hold_the_metrics_records_the_learning_rate_and_the_pictures_across_a_resume(tmp_path):
    """Trained to step 2 (the data ends there), then resumed to 4: the second run marks its start for
    TensorBoard to drop anything the first wrote past its checkpoint."""
    train.train(CFG, str(tmp_path), batches=lambda start: batches(start, stop=2))
    train.train(CFG, str(tmp_path), batches=batches)
    scalars, images, starts = board_contents(tmp_path)
    records = read_jsonl(tmp_path / "metrics.jsonl")
    assert [r["step"] for r in records] == [1, 2, 3, 4] and starts == [2]
    for record in records:
        for name, value in record.items():
            if name != "step":
                tag = (
                    name
                    if name in ("grad_norm", "steps_per_s", "nonfinite_in_a_row", "nonfinite_total")
                    else f"loss/{name}"
                )
                assert scalars[tag][record["step"]] == pytest.approx(value, rel=1e-6), tag
        assert scalars["learning_rate"][record["step"]] == pytest.approx(CFG.train.learning_rate)
    r, n = CFG.data.image_size, pose_belief.grid_of(CFG.model).n
    assert sorted(images) == sorted(
        (tag, step)
        for step in (2, 4)
        for tag in ("reconstruction/camera", "reconstruction/lidar", "reconstruction/roadmap", "pose_belief")
    )
    camera = images[("reconstruction/camera", 4)]
    assert camera.shape == (r, 2 * r, 3)
    np.testing.assert_array_equal(camera[:, :r], synthetic_batch(3, TINY)["camera"][0, -1])  # the input, left
    belief = images[("pose_belief", 4)]
    assert belief.shape == (n, n, 3)
    green = np.argwhere((belief[..., 1] == 255) & (belief[..., 0] == 0))
    pose = synthetic_batch(3, TINY)["pose"][0, -1]
    col, row = np.clip(
        np.floor((pose[:2] - pose_belief.AREA_ORIGIN_M) / pose_belief.grid_of(CFG.model).cell_m), 0, n - 1
    )
    assert green.tolist() == [[n - 1 - int(row), int(col)]]  # the true cell, north up


@pytest.mark.slow
def test_without_tensorboardx_training_runs_and_says_so(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "tensorboardX", None)  # import tensorboardX now raises ImportError
    state = train.train(tiny(num_steps=2, checkpoint_every=2, log_every=1), str(tmp_path), batches=batches)
    assert int(state.step) == 2 and [r["step"] for r in read_jsonl(tmp_path / "metrics.jsonl")] == [1, 2]
    assert "tensorboardX is not installed" in capsys.readouterr().out
    assert not glob.glob(f"{tmp_path}/events.out.tfevents.*")
