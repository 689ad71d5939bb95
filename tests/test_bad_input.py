"""Bad input, one table: launcher flags, inference-API arguments, damaged run directories.

Every row fails in one line that names the flag or the file: a launcher exits with status 1 and writes
exactly one line to stderr, ``error: ...``; the Python API raises a ValueError with a one-line message.
A line about a run directory (rows with a ``damage``) is under ``LINE_LIMIT`` characters; a damaged
checkpoint's also says what was done about it and what to do.
Nothing is written to the run directory (every file and folder compared before and after), and nothing
is compiled (launchers run under JAX_LOG_COMPILES=1, which logs each compilation to stderr; in-process
rows under ``jax.log_compiles``). A few rows are inputs the API must accept.

The damaged runs are copies of ONE tiny run trained here (2 steps, a checkpoint after each). Resuming
training past damaged latest checkpoints is not a failure: it sets each aside as ``<step>.damaged`` (or
``<step>.damaged.2``, ... when that name is taken) and goes on from the newest intact one; the tests at the
end check it.
"""

import concurrent.futures
import contextlib
import dataclasses
import hashlib
import logging
import os
import re
import shutil
import subprocess
import sys
from typing import Any, NamedTuple

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest
from helpers import ROOT, TINY, environment, read_jsonl, synthetic_batch, xla_flags

import e2e_percep_jax as e2e
from e2e_percep_jax import checkpoint
from e2e_percep_jax import config as config_lib
from e2e_percep_jax import train as train_lib
from e2e_percep_jax.sim.motion import MotionModel

CFG = config_lib.replace(TINY, train=dict(num_steps=2, checkpoint_every=1, log_every=1))  # the run's config
R, Z1, Z2 = TINY.data.image_size, TINY.model.z1_dim, TINY.model.z2_dim
FOREIGN = config_lib.replace(CFG, model=dict(hidden_dim=TINY.model.hidden_dim // 2))  # another model width
FOUR_DEVICES = {"XLA_FLAGS": xla_flags("--xla_force_host_platform_device_count=4")}
PARALLEL = 6  # launcher subprocesses at once: CPU-bound imports on 2 cores, so more buys nothing
LINE_LIMIT = 200  # characters of the line about a damaged run, its paths counted by their last part


def length(line):
    """The line's length with each path counted as its last part: how deep the user's run directory lies
    is not the message's length."""
    return len(re.sub(r"(?:/[^/\s;:,]+)+/([^/\s;:,]+)", r"\1", line))


class Case(NamedTuple):
    """``target``: train | evaluate | occlusion_strip | building_occlusion (the launchers, with ``args`` their flags), load (``e2e.load`` with
    ``args`` its keywords), init | init under jit | init traced (``Perceiver.init(*args)``; under jit with
    the batch size static, or traced), step | step under jit (``Perceiver.step``, ``args`` replacing some
    of its good inputs, each made by a function), accepted (a step that must succeed and equal the same
    step on float32 arrays). ``expect``: how the error message starts, or with a leading "…" a part of
    it. ``damage``: what is done to the run copied for the row (:func:`damage`); launcher rows without it
    get a fresh --workdir (train) or an intact copy (the others). ``env``: more environment for a launcher."""

    target: str
    args: Any
    expect: str = ""
    damage: str | None = None
    env: dict | None = None


def _state(**parts):
    """Perceiver.init(2) with some of its fields replaced (``pose_speed_mps=None`` drops that leaf)."""
    state = e2e.Perceiver(CFG).init(2)
    pose = {name[len("pose_") :]: value for name, value in parts.items() if name.startswith("pose_")}
    state = state.replace(pose=state.pose.replace(**pose))
    return state.replace(**{name: value for name, value in parts.items() if not name.startswith("pose_")})


_F32, _U8 = np.float32, np.uint8
_images = lambda b=2, r=R, dtype=_U8: np.zeros((b, r, r, 3), dtype)

CASES = {
    # ---------------------------------------------------------------- experiments/train.py, a fresh --workdir
    "train image_size not a power of two": Case(
        "train", ["--data.image_size=48"], "--data.image_size=48: must be a power of two >= 32"
    ),
    "train image_size too small": Case(
        "train", ["--data.image_size=16"], "--data.image_size=16: must be a power of two >= 32"
    ),
    "train image_size beyond the conv widths": Case(
        "train", ["--data.image_size=256"], "--model.conv_channels has 3 widths; image_size 256 needs 6"
    ),
    "train variant": Case("train", ["--model.variant=both"], "--model.variant='both': choose one of"),
    "train latent": Case("train", ["--model.latent=grid"], "--model.latent='grid': choose one of"),
    "train observation_drop_share of one": Case(
        "train", ["--train.observation_drop_share=1"], "--train.observation_drop_share=1.0: must lie in [0, 1)"
    ),
    "train lidar_shadow_share negative": Case(
        "train", ["--train.lidar_shadow_share=-0.1"], "--train.lidar_shadow_share=-0.1: must lie in [0, 1)"
    ),
    "train vanish_share above one": Case(
        "train", ["--data.vanish_share=1.5"], "--data.vanish_share=1.5: must lie in [0, 1]"
    ),
    "train occluder_share negative": Case(
        "train", ["--data.occluder_share=-0.5"], "--data.occluder_share=-0.5: must lie in [0, 1]"
    ),
    "train remembered_weight zero": Case(
        "train", ["--train.remembered_weight=0"], "--train.remembered_weight=0.0: must be positive"
    ),
    "train unseen_weight negative": Case(
        "train", ["--train.unseen_weight=-1"], "--train.unseen_weight=-1.0: must be at least 0"
    ),
    "train grid_update": Case(
        "train",
        ["--model.latent=bev", "--model.grid_update=occupancy"],
        "--model.grid_update='occupancy': choose one of",
    ),
    "train grid_update without the grid": Case(
        "train", ["--model.grid_update=lidar_gated"], "--model.grid_update='lidar_gated' updates the bird-eye grid"
    ),
    "train grid_warp without the grid": Case(
        "train", ["--model.grid_warp=lattice"], "--model.grid_warp='lattice' carries the bird-eye grid"
    ),
    "train lidar_decoder_input": Case(
        "train",
        ["--model.latent=bev", "--model.lidar_decoder_input=features"],
        "--model.lidar_decoder_input='features': choose one of",
    ),
    "train detection from the grid without the grid": Case(
        "train", ["--model.detection_input=grid"], "--model.detection_input=grid reads the bird-eye grid"
    ),
    "train grid_cells not a size the trunk passes": Case(
        "train", ["--model.latent=bev", "--model.grid_cells=12"], "--model.grid_cells=12: must be a power of two in"
    ),
    "train grid_cells above half the image": Case(
        "train", ["--model.latent=bev", "--model.grid_cells=32"], "--model.grid_cells=32: must be a power of two in"
    ),
    "train grid_memory_channels negative": Case(
        "train", ["--model.grid_memory_channels=-1"], "--model.grid_memory_channels=-1: must be >= 0"
    ),
    "train grid_memory_channels on the vector latent": Case(
        "train",
        ["--model.latent=vector", "--model.grid_memory_channels=4"],
        "--model.grid_memory_channels=4: must be >= 0, and > 0 only with --model.latent=bev",
    ),
    "train batch_size zero": Case("train", ["--data.batch_size=0"], "--data.batch_size=0: must be positive"),
    "train batch_size not a multiple of the devices": Case(
        "train",
        ["--data.batch_size=3"],
        "--data.batch_size=3 must be a multiple of the number of devices (4)",
        env=FOUR_DEVICES,
    ),
    "train conv_channels zero": Case(
        "train", ["--model.conv_channels=8,0,32"], "--model.conv_channels[1]=0: must be positive"
    ),
    "train conv_channels negative": Case(
        "train", ["--model.conv_channels=8,-16,32"], "--model.conv_channels[1]=-16: must be positive"
    ),
    "train conv_channels not integers": Case(
        "train", ["--model.conv_channels=8,x"], "--model.conv_channels=8,x: expected comma-separated integers"
    ),
    "train unknown field": Case("train", ["--data.nonsense=1"], "Unknown command line flag 'data.nonsense'"),
    "train unknown preset": Case("train", ["--config=nope"], "--config='nope' is not a preset"),
    "train vehicles beyond the town": Case(
        "train", ["--world.num_vehicles=100000"], "--world.num_vehicles=100000: at most"
    ),
    "train negative town seed": Case("train", ["--world.town_seed=-1"], "--world.town_seed=-1: must be >= 0"),
    "train negative seed": Case("train", ["--train.seed=-1"], "--train.seed=-1: must be >= 0"),
    "train negative warm-up": Case("train", ["--data.warmup_steps=-1"], "--data.warmup_steps=-1: must be >= 0"),
    "train batches_per_drive zero": Case(
        "train", ["--data.batches_per_drive=0"], "--data.batches_per_drive=0: must be positive"
    ),
    "train carry_state with one batch per drive": Case(
        "train", ["--data.carry_state"], "--data.carry_state: needs segments to carry across"
    ),
    "train lr_decay_share of 1": Case(
        "train", ["--train.lr_decay_share=1"], "--train.lr_decay_share=1.0: must lie in [0, 1)"
    ),
    "train soft targets of zero width": Case(
        "train", ["--model.pose_target_std_cells=0"], "--model.pose_target_std_cells=0.0: must lie in (0, 5] cells"
    ),
    "train negative max_grad_norm": Case(
        "train", ["--train.max_grad_norm=-1"], "--train.max_grad_norm=-1.0: must be >= 0"
    ),
    "train negative actuator lag": Case(
        "train", ["--world.ego_lag_s=-0.1"], "--world.ego_lag_s=-0.1: must lie in [0, 1]"
    ),
    "train steering gain spread too wide": Case(
        "train", ["--world.ego_steer_gain_std=0.5"], "--world.ego_steer_gain_std=0.5: must lie in [0, 0.2]"
    ),
    "train negative pose_weight": Case("train", ["--train.pose_weight=-1"], "--train.pose_weight=-1.0: must be >= 0"),
    "train negative pose_hidden_dim": Case(
        "train", ["--model.pose_hidden_dim=-1"], "--model.pose_hidden_dim=-1: must be >= 0"
    ),
    "train kl_weight zero": Case("train", ["--train.kl_weight=0"], "--train.kl_weight=0.0: must be positive"),
    "train pose_filter": Case("train", ["--model.pose_filter=kalman"], "--model.pose_filter='kalman': choose one of"),
    "train known_start without the filter": Case(
        "train",
        ["--eval.known_start", "--model.pose_filter=none"],
        "--eval.known_start: needs the belief pose head and its filter",
    ),
    "train score_threshold": Case(
        "train", ["--eval.score_threshold=1.5"], "--eval.score_threshold=1.5: must lie in (0, 1)"
    ),
    "train detection_drives negative": Case(
        "train", ["--eval.detection_drives=-1"], "--eval.detection_drives=-1: must be >= 0"
    ),
    "train detection_pool below its drives": Case(
        "train",
        ["--eval.detection_drives=8", "--eval.detection_pool=4"],
        "--eval.detection_pool=4: must be 0 (no choice) or at least --eval.detection_drives=8",
    ),
    "train spread_frames zero": Case("train", ["--eval.spread_frames=0"], "--eval.spread_frames=0: must be positive"),
    "train spread towns holding the training town": Case(
        "train",
        ["--eval.spread_town_seeds=101,0"],
        "--eval.spread_town_seeds=101,0: must name one or more town seeds >= 0, neither the training town",
    ),
    "train spread towns holding the evaluated town": Case(
        "train",
        ["--eval.town_seed=7", "--eval.spread_town_seeds=7"],
        "--eval.spread_town_seeds=7: must name one or more town seeds >= 0, neither the training town "
        "(--world.town_seed=0) nor the evaluated one (--eval.town_seed=7)",
    ),
    "train a positional argument": Case("train", ["extra"], "unexpected arguments ['extra']"),
    "train no workdir": Case("train", ["--workdir="], "--workdir is required"),
    # ---------------------------------------------------------------- experiments/train.py resuming the run
    "train resume with another z1_dim": Case(
        "train", ["--model.z1_dim=4"], "--model.z1_dim=4 differs from the run being resumed", damage="none"
    ),
    "train resume with other conv widths": Case(
        "train", ["--model.conv_channels=8,16,64"], "…pass --model.conv_channels=8,16,32 to resume it", damage="none"
    ),
    "train resume, config.json not JSON": Case(
        "train", [], "…/config.json: not a config (JSONDecodeError", damage="config.json not JSON"
    ),
    "train resume, config.json with an unknown field": Case(
        "train", [], "…/config.json: not a config", damage="config.json with an unknown field"
    ),
    "train resume, config.json of another model": Case(
        "train",
        [],
        f"…; pass --model.z1_dim={Z1 + 1} to resume it, or use a new --workdir",
        damage="config.json of another model",
    ),
    "train resume, no config.json": Case("train", [], "…: no config.json", damage="no config.json"),
    # ---------------------------------------------------------------- experiments/evaluate.py on the run
    "evaluate top_k": Case("evaluate", ["--eval.top_k=-1"], "--eval.top_k=-1: must be positive"),
    "evaluate nms_iou": Case("evaluate", ["--eval.nms_iou=7"], "--eval.nms_iou=7.0: must lie in (0, 1]"),
    "evaluate nms_merge_iou": Case(
        "evaluate", ["--eval.nms_merge_iou=0.2"], "--eval.nms_merge_iou=0.2: must lie in [--eval.nms_iou=0.3, 1]"
    ),
    "evaluate score_floor": Case("evaluate", ["--eval.score_floor=-3"], "--eval.score_floor=-3.0: must lie in [0, 1)"),
    "evaluate video_frames": Case("evaluate", ["--video_frames=-1"], "--video_frames and --num_examples must be >= 0"),
    "evaluate negative step": Case("evaluate", ["--step=-2"], "--step=-2: "),
    "evaluate step not saved": Case("evaluate", ["--step=999"], "--step=999: "),
    "evaluate a trained-model field": Case(
        "evaluate",
        ["--model.z1_dim=4"],
        "--model.z1_dim: only --eval.*, --model.pose_filter and the plant's --world.ego_* may change",
    ),
    "evaluate a preset": Case("evaluate", ["--config=tiny"], "--config: the run's config.json is the config"),
    "evaluate negative town seed": Case("evaluate", ["--eval.town_seed=-1"], "--eval.town_seed=-1: must be >= 0"),
    "evaluate no workdir": Case("evaluate", ["--workdir="], "--workdir is required"),
    "evaluate not a run": Case("evaluate", ["--workdir=/nonexistent/run"], "/nonexistent/run: no config.json"),
    # ---------------------------------------------------------------- experiments/occlusion_strip.py on the run
    "occlusion strip drives": Case(
        "occlusion_strip", ["--drives=0"], "--drives=0 and --min_hidden=10 must each be >= 1"
    ),
    "occlusion strip without detection drives": Case(
        "occlusion_strip", [], "…: its evaluation has no detection drives to search"
    ),
    "occlusion strip not a run": Case(
        "occlusion_strip", ["--workdir=/nonexistent/run"], "/nonexistent/run: no config.json"
    ),
    "occlusion strip behind": Case(
        "occlusion_strip", ["--behind=wall"], "flag --behind=wall: value should be one of <any|vehicle|town>"
    ),
    # ---------------------------------------------------------------- experiments/building_occlusion.py on the run
    "building occlusion speed": Case(
        "building_occlusion", ["--speed_mps=0"], "--speed_mps=0.0: must lie in [0.5, 10] (a vehicle crossing"
    ),
    "building occlusion not a run": Case(
        "building_occlusion", ["--workdir=/nonexistent/run"], "/nonexistent/run: no config.json"
    ),
}
# Every damaged run through both readers, e2e.load and the evaluation launcher: each names the checkpoint or the
# config.json it could not use (training's resume is in the "train resume" rows above and the tests at the end).
_DAMAGED = "…/checkpoints/2: cannot be restored (damaged); stopped, nothing changed: use an older step (1)"
_OTHER_CONFIG = (
    "…/checkpoints/2: cannot be restored (holds another network); stopped, nothing changed: use its training config"
)
DAMAGES = {  # damage: what the message says (Case.expect)
    "array files truncated": _DAMAGED,
    "array files truncated to zero bytes": _DAMAGED,
    "checkpoint overwritten with random bytes": _DAMAGED,
    "empty step folder": _DAMAGED,
    "checkpoint of another model width": _OTHER_CONFIG,
    "config.json not JSON": "…/config.json: not a config (JSONDecodeError",
    "config.json with an unknown field": "…/config.json: not a config (ValueError: config.json: unknown fields "
    "['image_sise'] in [data])",
    "config.json of another model": _OTHER_CONFIG,
    "no config.json": "…: no config.json",
    "no checkpoints": "no checkpoint in ",
}
for _damage, _expect in DAMAGES.items():
    CASES[f"load, {_damage}"] = Case("load", {}, _expect, damage=_damage)
    CASES[f"evaluate, {_damage}"] = Case("evaluate", [], _expect, damage=_damage)
CASES.update(
    {
        # ---------------------------------------------------------------- e2e.load, Perceiver.init and .step
        "load step not saved": Case("load", {"step": 3}, "--step=3: ", damage="none"),
        "init negative": Case("init", [-1], "batch_size=-1: must be a positive integer"),
        "init zero": Case("init", [0], "batch_size=0: must be a positive integer"),
        "init a float": Case("init", [2.5], "batch_size=2.5: must be a positive integer"),
        "init a bool": Case("init", [True], "batch_size=True: must be a positive integer"),
        "init a string": Case("init", ["2"], "batch_size='2': must be a positive integer"),
        "init None": Case("init", [None], "batch_size=None: must be a positive integer"),
        "init under jit, negative": Case("init under jit", [-1], "batch_size=-1: must be a positive integer"),
        "init traced under jit": Case("init traced", [2], "…: must be a positive integer"),  # a shape must be static
    }
)
_IMAGE = f"uint8[2, {R}, {R}, 3]"
_STEP_CASES = {  # replaced inputs -> message
    "camera dtype": (
        {"camera": lambda: _images(dtype=_F32)},
        f"camera: expected {_IMAGE}, got float32[2, {R}, {R}, 3]",
    ),
    "camera size": (
        {"camera": lambda: _images(r=R // 2)},
        f"camera: expected {_IMAGE}, got uint8[2, {R // 2}, {R // 2}, 3]",
    ),
    "camera batch": ({"camera": lambda: _images(b=3)}, f"camera: expected {_IMAGE}, got uint8[3, {R}, {R}, 3]"),
    "camera without the batch axis": (
        {"camera": lambda: _images()[0]},
        f"camera: expected {_IMAGE}, got uint8[{R}, {R}, 3]",
    ),
    "lidar size": (
        {"lidar": lambda: _images(r=R // 2)},
        f"lidar: expected {_IMAGE}, got uint8[2, {R // 2}, {R // 2}, 3]",
    ),
    "lidar dtype": ({"lidar": lambda: _images(dtype=np.int32)}, f"lidar: expected {_IMAGE}, got int32[2, {R}, {R}, 3]"),
    "action width": ({"action": lambda: np.zeros((2, 3), _F32)}, "action: expected float32[2, 2], got float32[2, 3]"),
    "action dtype": ({"action": lambda: np.zeros((2, 2), np.int32)}, "action: expected float32[2, 2], got int32[2, 2]"),
    "action batch": ({"action": lambda: np.zeros((3, 2), _F32)}, "action: expected float32[2, 2], got float32[3, 2]"),
    "start_pose width": (
        {"start_pose": lambda: np.zeros((2, 4), _F32)},
        "start_pose: expected float32[2, 5], got float32[2, 4]",
    ),
    "z1 width": (
        {"state": lambda: _state(z1=np.zeros((2, Z1 + 1), _F32))},
        f"state.z1: expected float32[2, {Z1}], got float32[2, {Z1 + 1}]",
    ),
    "z2 batch": (
        {"state": lambda: _state(z2=np.zeros((3, Z2), _F32))},
        f"state.z2: expected float32[2, {Z2}], got float32[3, {Z2}]",
    ),
    "z1 dtype": (
        {"state": lambda: _state(z1=np.zeros((2, Z1), np.float16))},
        f"state.z1: expected float32[2, {Z1}], got float16[2, {Z1}]",
    ),
    "first dtype": (
        {"state": lambda: _state(first=np.zeros(2, np.int32))},
        "state.first: expected bool[2], got int32[2]",
    ),
    "pose belief shape": (
        {"state": lambda: _state(pose_belief=np.zeros((2, 1, 1, 1), _F32))},
        "state.pose.belief: expected float32[2, ",
    ),
    "state missing a part": (
        {"state": lambda: _state(pose_speed_mps=None)},
        "state: expected the FilterState of Perceiver.init; missing ['state.pose.speed_mps'], unexpected []",
    ),
    "state without the pose belief": (
        {"state": lambda: _state(pose=None)},
        "state: expected the FilterState of Perceiver.init; missing ['state.pose'], unexpected []",
    ),
    "state as a dict of its fields": (
        {"state": lambda: dataclasses.asdict(_state())},
        "state: expected the FilterState of Perceiver.init, got dict",
    ),
    "state None": ({"state": lambda: None}, "state: expected the FilterState of Perceiver.init, got NoneType"),
}
for _name, (_args, _expect) in _STEP_CASES.items():
    CASES[f"step {_name}"] = Case("step", _args, _expect)
    CASES[f"step under jit, {_name}"] = Case("step under jit", _args, _expect)
CASES.update(
    {  # array-likes NumPy takes as float32 [2, 2]
        "accepted: action as a list": Case("accepted", {"action": lambda: [[0.5, -0.1], [0.0, 0.2]]}),
        "accepted: action as a tuple": Case("accepted", {"action": lambda: ((0.5, -0.1), (0.0, 0.2))}),
        "accepted: action as float64": Case("accepted", {"action": lambda: np.array([[0.5, -0.1], [0.0, 0.2]])}),
    }
)
LAUNCHERS = ("train", "evaluate", "occlusion_strip", "building_occlusion")


# ----------------------------------------------------------------------------- the run and its damages


def synthetic_batches(start):
    """The run's batches: random frames of the frame contract (no world, so nothing to compile but the step)."""
    step = start
    while True:
        yield step, synthetic_batch(step, CFG)
        step += 1


def _files(folder):
    return sorted(os.path.join(d, f) for d, _, names in os.walk(folder) for f in names)


def damage(run, how, foreign, step=2):
    """Damages the run copied to ``run`` (its latest checkpoint is step 2) as ``how`` says; a damage to a
    checkpoint, to checkpoint ``step``."""
    step = os.path.join(run, "checkpoints", str(step))
    config_path = os.path.join(run, "config.json")
    if how.startswith("array files truncated"):  # the OCDBT data files, where the arrays are
        arrays = [p for p in _files(step) if os.path.basename(os.path.dirname(p)) == "d"]
        assert arrays, _files(step)
        for path in arrays:
            with open(path, "r+b") as f:
                f.truncate(0 if how.endswith("to zero bytes") else os.path.getsize(path) // 2)
    elif how == "checkpoint overwritten with random bytes":
        rng = np.random.default_rng(0)
        for path in _files(step):
            with open(path, "wb") as f:
                f.write(rng.bytes(max(os.path.getsize(path), 16)))
    elif how == "empty step folder":
        shutil.rmtree(step)
        os.mkdir(step)
    elif how == "checkpoint of another model width":
        shutil.rmtree(step)
        shutil.copytree(os.path.join(foreign, "checkpoints", "2"), step)
    elif how == "config.json not JSON":
        with open(config_path, "w") as f:
            f.write("{ not json")
    elif how == "config.json with an unknown field":
        with open(config_path, "w") as f:
            f.write('{"data": {"image_sise": 64}}')
    elif how == "config.json of another model":
        with open(config_path, "w") as f:
            f.write(config_lib.replace(CFG, model=dict(z1_dim=Z1 + 1)).to_json())
    elif how == "no config.json":
        os.remove(config_path)
    elif how == "no checkpoints":
        shutil.rmtree(os.path.join(run, "checkpoints"))
    else:
        assert how == "none", how


def snapshot(folder):
    """Every file (its bytes' digest) and folder under ``folder``; None if it does not exist."""
    if not os.path.exists(folder):
        return None
    tree = {os.path.relpath(d, folder) + "/": "folder" for d, _, _ in os.walk(folder)}
    for path in _files(folder):
        with open(path, "rb") as f:
            tree[os.path.relpath(path, folder)] = hashlib.sha256(f.read()).hexdigest()
    return tree


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """(the tiny run: CFG trained 2 steps, checkpoints 1 and 2; a folder whose checkpoints/2 holds a checkpoint
    of FOREIGN)."""
    path = str(tmp_path_factory.mktemp("run"))
    train_lib.train(CFG, path, batches=synthetic_batches)
    MotionModel().save(path)  # (trained on synthetic batches, so no motion model was fitted on the world)
    assert checkpoint.saved_steps(path) == [1, 2]
    foreign = str(tmp_path_factory.mktemp("foreign"))
    with checkpoint.manager(foreign) as manager:
        manager.save(2, args=ocp.args.StandardSave(train_lib.init_state(FOREIGN)))
    return path, foreign


def _launcher_run(case, workdir, env):
    cmd = [sys.executable, os.path.join(ROOT, "experiments", f"{case.target}.py"), *case.args]
    if not any(a.startswith("--workdir") for a in case.args):
        cmd.append(f"--workdir={workdir}")
    if case.target == "train" and not any(a.startswith("--config") for a in case.args):
        cmd.append("--config=tiny")
    proc = subprocess.run(
        cmd,
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=600,
        env={**env, "JAX_LOG_COMPILES": "1", **(case.env or {})},
    )
    return proc.returncode, proc.stderr, snapshot(workdir)


@pytest.fixture(scope="module")
def launched(run, tmp_path_factory):
    """Every launcher row started at once (PARALLEL at a time) on its own workdir; name -> a future of
    (exit status, stderr, the workdir's snapshot after) and the snapshot before; the threads get the
    environment as ``helpers.environment`` copies it here, in the main thread."""
    root, env = tmp_path_factory.mktemp("launched"), environment()
    pool = concurrent.futures.ThreadPoolExecutor(PARALLEL)
    started = {}
    for i, (name, case) in enumerate(CASES.items()):
        if case.target not in LAUNCHERS:
            continue
        workdir = str(root / str(i))
        if case.damage is not None or case.target != "train":  # the others read the trained run
            shutil.copytree(run[0], workdir)
            damage(workdir, case.damage or "none", run[1])
        started[name] = (pool.submit(_launcher_run, case, workdir, env), snapshot(workdir))
    yield started
    pool.shutdown(cancel_futures=True)


@contextlib.contextmanager
def no_compiles():
    """Fails if anything is compiled inside (jax logs each compilation under ``jax.log_compiles``)."""

    class Compiles(logging.Handler):
        def __init__(self):
            super().__init__(logging.WARNING)
            self.messages = []

        def emit(self, record):
            if record.getMessage().startswith("Compiling "):
                self.messages.append(record.getMessage())

    handler, logger = Compiles(), logging.getLogger("jax")
    logger.addHandler(handler)
    try:
        with jax.log_compiles(True):
            yield
    finally:
        logger.removeHandler(handler)
    assert not handler.messages, handler.messages


@pytest.fixture(scope="module")
def params(run):
    """The run's params, through the API (the intact run loads)."""
    perceiver, params = e2e.load(run[0])
    assert perceiver.cfg == CFG
    return params


def says(message, expect):
    return expect[1:] in message if expect.startswith("…") else message.startswith(expect)


def _step_inputs(case):
    good = {
        "state": lambda: _state(),
        "camera": _images,
        "lidar": _images,
        "action": lambda: np.zeros((2, 2), _F32),
        "start_pose": lambda: None,
    }
    return {k: make() for k, make in dict(good, **case.args).items()}


# ----------------------------------------------------------------------------- the table


# The launcher rows are slow together: the first one starts all of them (``launched``).
@pytest.mark.parametrize(
    "name",
    [pytest.param(name, marks=pytest.mark.slow) if case.target in LAUNCHERS else name for name, case in CASES.items()],
)
def test_bad_input_fails_in_one_line_naming_it_and_writes_nothing(name, request, tmp_path):
    case = CASES[name]
    if case.target in LAUNCHERS:
        future, before = request.getfixturevalue("launched")[name]
        status, err, after = future.result()
        lines = err.splitlines()
        # JAX_LOG_COMPILES logs tracing too: evaluate traces the train state's shapes (jax.eval_shape) to
        # restore a checkpoint; that is not a compilation, and without the variable it prints nothing.
        compiled = [ln for ln in lines if "Compiling " in ln or "XLA compilation" in ln or "MLIR module" in ln]
        said = [ln for ln in lines if "Finished tracing" not in ln]
        assert status == 1 and len(said) == 1 and said[0].startswith("error: ") and says(said[0][7:], case.expect), (
            status,
            err,
        )
        assert not compiled, err
        assert case.damage is None or length(said[0]) < LINE_LIMIT, said[0]
        assert after == before  # nothing written, deleted or changed; a fresh --workdir not even made
        return
    if case.target == "accepted":
        inputs = _step_inputs(case)
        perceiver, params = e2e.Perceiver(CFG), request.getfixturevalue("params")
        _, got = perceiver.step(params, inputs["state"], inputs["camera"], inputs["lidar"], inputs["action"])
        _, want = perceiver.step(
            params, inputs["state"], inputs["camera"], inputs["lidar"], np.asarray(inputs["action"], _F32)
        )
        jax.tree.map(np.testing.assert_array_equal, got, want)
        return
    perceiver = e2e.Perceiver(CFG)
    workdir = before = None
    if case.target == "load":
        run, workdir = request.getfixturevalue("run"), str(tmp_path / "run")
        shutil.copytree(run[0], workdir)
        damage(workdir, case.damage, run[1])
        before = snapshot(workdir)
        call = lambda: e2e.load(workdir, **case.args)
    elif case.target.startswith("init"):
        init = {
            "init": perceiver.init,
            "init under jit": jax.jit(perceiver.init, static_argnums=0),
            "init traced": jax.jit(perceiver.init),
        }[case.target]
        call = lambda: init(*case.args)
    else:
        inputs = _step_inputs(case)
        step = jax.jit(perceiver.step) if "jit" in case.target else perceiver.step
        params = request.getfixturevalue("params")
        call = lambda: step(
            params,
            inputs["state"],
            inputs["camera"],
            inputs["lidar"],
            inputs["action"],
            start_pose=inputs["start_pose"],
        )
    # Eager step: putting new NumPy shapes on the device compiles a copy in some jax versions, valid or not;
    # the checks themselves run at trace time, compiling nothing, as the rows under jit show.
    guard = contextlib.nullcontext() if case.target == "step" else no_compiles()
    with guard, pytest.raises(ValueError) as error:
        call()
    message = str(error.value)
    limit = 600 if case.damage is None else LINE_LIMIT
    assert "\n" not in message and says(message, case.expect) and length(message) < limit, message
    if workdir is not None:
        assert snapshot(workdir) == before


# ----------------------------------------------------------------------------- resuming a damaged run

RESUME = ["--train.num_steps=2", "--train.checkpoint_every=1", "--train.log_every=1"]  # --config=tiny as CFG


def _resumed(workdir, args=()):
    """(exit status, stderr lines, snapshots before and after) of experiments/train.py resuming run ``workdir``
    under CFG and ``args``; without compile logs, as a person runs it (the resume compiles the step)."""
    before = snapshot(workdir)
    status, err, after = _launcher_run(
        Case("train", [*RESUME, *args], env={"JAX_LOG_COMPILES": "0"}), workdir, os.environ
    )
    return status, err.splitlines(), before, after


def _under(tree, folder):
    """The part of snapshot ``tree`` under ``folder`` (relative to the run), named relative to it."""
    return {name[len(folder) :]: digest for name, digest in tree.items() if name.startswith(folder + "/")}


@pytest.mark.parametrize(
    "how",
    [
        "array files truncated",
        "array files truncated to zero bytes",
        "checkpoint overwritten with random bytes",
        "empty step folder",
        "checkpoint of another model width",
    ],
)
@pytest.mark.slow
def test_a_resume_sets_a_damaged_latest_checkpoint_aside(run, tmp_path, capfd, how):
    """Training resumed on a run whose latest checkpoint is damaged says so in one line, renames that one
    (its files untouched) to ``2.damaged``, resumes from step 1 (untouched, as is config.json) and ends
    where the undamaged run ended."""
    workdir = str(tmp_path / "run")
    shutil.copytree(run[0], workdir)
    damage(workdir, how, run[1])
    before = snapshot(workdir)
    capfd.readouterr()
    state = train_lib.train(CFG, workdir, batches=synthetic_batches)
    out, err = capfd.readouterr()
    step2 = os.path.join(workdir, "checkpoints", "2")
    why = "holds another network" if how == "checkpoint of another model width" else "damaged"
    line = f"checkpoint {step2}: cannot be restored ({why}); kept as 2.damaged, resumed from step 1"
    assert [ln for ln in err.splitlines() if ln.startswith("checkpoint ")] == [line] and length(line) < LINE_LIMIT, err
    assert f"resumed from step 1 in {workdir}" in out
    after = snapshot(workdir)
    kept = {k: v for k, v in before.items() if k.startswith("checkpoints/2/")}
    assert {k.replace("checkpoints/2", "checkpoints/2.damaged", 1): v for k, v in kept.items()} == {
        k: v for k, v in after.items() if k.startswith("checkpoints/2.damaged")
    }
    for name, digest in before.items():
        if name == "config.json" or name.startswith("checkpoints/1/"):
            assert after[name] == digest, name
    records, undamaged = (read_jsonl(os.path.join(path, "metrics.jsonl")) for path in (workdir, run[0]))
    assert records[0] == undamaged[0] and [r["step"] for r in records] == [1, 2]  # step 1's record kept
    timeless = lambda record: {k: v for k, v in record.items() if k != "steps_per_s"}
    assert timeless(records[1]) == timeless(undamaged[1])
    assert int(state.step) == 2 and checkpoint.saved_steps(workdir) == [1, 2]
    jax.tree.map(
        np.testing.assert_array_equal, checkpoint.restore_params(workdir)[1], checkpoint.restore_params(run[0])[1]
    )


@pytest.mark.slow
def test_a_resume_past_two_damaged_checkpoints_keeps_both(run, tmp_path):
    """The two newest checkpoints damaged (a step 3 whose array files were cut to zero bytes, step 2 truncated):
    the launcher resumes from step 1 with one line for each, kept file for file as 3.damaged and 2.damaged."""
    workdir = str(tmp_path / "run")
    shutil.copytree(run[0], workdir)
    shutil.copytree(os.path.join(workdir, "checkpoints", "2"), os.path.join(workdir, "checkpoints", "3"))
    damage(workdir, "array files truncated to zero bytes", run[1], step=3)
    damage(workdir, "array files truncated", run[1])
    status, lines, before, after = _resumed(workdir)
    expected = [
        f"checkpoint {workdir}/checkpoints/{step}: cannot be restored (damaged); kept as {step}.damaged, "
        "resumed from step 1"
        for step in (3, 2)
    ]
    assert status == 0 and lines == expected and max(map(length, expected)) < LINE_LIMIT, lines
    for step in (3, 2):
        assert _under(after, f"checkpoints/{step}.damaged") == _under(before, f"checkpoints/{step}"), step
    kept = _under(before, "checkpoints/1")
    assert len(kept) > 1 and _under(after, "checkpoints/1") == kept
    assert after["config.json"] == before["config.json"] and checkpoint.saved_steps(workdir) == [1, 2]


@pytest.mark.slow
def test_a_resume_keeps_a_damaged_checkpoint_under_the_first_free_name(run, tmp_path):
    """Step 2 damaged where an earlier resume already kept a step 2 as 2.damaged (a folder of files): the
    launcher keeps the new one as 2.damaged.2 and resumes from step 1, in one line; the old one stays as it was."""
    workdir = str(tmp_path / "run")
    shutil.copytree(run[0], workdir)
    shutil.copytree(os.path.join(run[1], "checkpoints", "2"), os.path.join(workdir, "checkpoints", "2.damaged"))
    damage(workdir, "array files truncated to zero bytes", run[1])
    status, lines, before, after = _resumed(workdir)
    line = f"checkpoint {workdir}/checkpoints/2: cannot be restored (damaged); kept as 2.damaged.2, resumed from step 1"
    assert status == 0 and lines == [line] and length(line) < LINE_LIMIT, lines
    assert _under(after, "checkpoints/2.damaged.2") == _under(before, "checkpoints/2")
    for kept in ("checkpoints/2.damaged", "checkpoints/1"):
        assert len(_under(before, kept)) > 1 and _under(after, kept) == _under(before, kept), kept
    assert after["config.json"] == before["config.json"] and checkpoint.saved_steps(workdir) == [1, 2]


@pytest.mark.slow
@pytest.mark.parametrize("trouble", ["every checkpoint damaged", "config.json of another model"])
def test_a_resume_with_no_checkpoint_that_restores_stops_in_one_line_changing_nothing(run, tmp_path, trouble):
    """No checkpoint restores for config.json, whether they are damaged or config.json is the odd one out
    (the checkpoints intact, the flags those of config.json): the launcher stops with one ``error:`` line that
    says what to do, and leaves every file and folder as it was, so a repaired config.json resumes the run.
    (The damaged run is resumed to more steps, a change a resume may make: config.json keeps the old count.)"""
    workdir = str(tmp_path / "run")
    shutil.copytree(run[0], workdir)
    if trouble == "every checkpoint damaged":
        for step in (1, 2):
            damage(workdir, "empty step folder", run[1], step=step)
        args, why, todo = [f"--train.num_steps={2 * CFG.train.num_steps}"], "damaged", "retrain in a new --workdir"
    else:
        cfg = config_lib.replace(CFG, model=dict(z1_dim=2 * CFG.model.z1_dim))
        with open(os.path.join(workdir, "config.json"), "w") as f:
            f.write(cfg.to_json())
        args = [f"--model.z1_dim={cfg.model.z1_dim}"]
        why, todo = "holds another network", "use its training config"
    status, lines, before, after = _resumed(workdir, args)
    line = f"error: {workdir}/checkpoints: no step restores (newest, 2: {why}); stopped, all kept: {todo}"
    assert status == 1 and lines == [line] and length(line) < LINE_LIMIT, lines
    assert after == before


def test_the_reports_of_reads_a_failed_restore_left_go_to_the_debug_log(run, tmp_path, caplog):
    """A failed restore leaves orbax's reads in flight; asyncio reports each one whose failure nobody retrieved,
    a page long, when it is collected (a moment after the one line). Those that name the checkpoint that failed
    go to the debug log; any other asyncio report is left as it is."""
    workdir = str(tmp_path / "run")
    shutil.copytree(run[0], workdir)
    damage(workdir, "array files truncated", run[1])
    with pytest.raises(ValueError):
        e2e.load(workdir)
    report = "Future exception was never retrieved\nfuture: <Future finished exception=ValueError('{}/default/')>"
    reports = [report.format(os.path.join(workdir, "checkpoints", step)) for step in ("2", "1")]
    with caplog.at_level(logging.DEBUG):
        for text in reports:
            logging.getLogger("asyncio").error(text)
    assert [(r.name, r.levelno, r.getMessage()) for r in caplog.records if "never retrieved" in r.getMessage()] == [
        ("e2e_percep_jax.config", logging.DEBUG, reports[0]),
        ("asyncio", logging.ERROR, reports[1]),
    ]
