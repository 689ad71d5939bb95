"""Configs: presets are valid and hashable, flags override exactly the named field, config.json round-trips.
(Bad values, each naming its flag, are rows of test_bad_input.py.)"""

import dataclasses
import json
import subprocess
import sys

import pytest
from absl import flags

from e2e_percep_jax import config as config_lib


def _parse(*argv):
    fv = flags.FlagValues()
    config_lib.define_flags(fv)
    fv(["prog", *argv])
    return config_lib.from_flags(fv)


@pytest.mark.parametrize("name", sorted(config_lib.PRESETS))
def test_presets_validate_and_are_hashable(name):
    cfg = config_lib.validate(config_lib.get_config(name))
    assert hash(cfg) == hash(dataclasses.replace(cfg))  # usable as a jit static argument
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.data.batch_size = 3


def test_paper_preset_is_the_papers_network_with_the_cpu_recipe():
    cfg, cpu = config_lib.get_config("paper"), config_lib.get_config("cpu")
    assert (cfg.data.image_size, cfg.data.seq_len, cfg.data.batch_size) == (128, 10, 32)
    assert cfg.model.conv_channels[:5] == (32, 64, 128, 256, 256)
    assert (cfg.model.z1_dim, cfg.model.z2_dim) == (32, 256)
    assert cfg.train == cpu.train and cfg.model.pose_hidden_dim == cpu.model.pose_hidden_dim
    assert (cfg.data.place_frames, cfg.data.batches_per_drive) == (cpu.data.place_frames, cpu.data.batches_per_drive)
    assert cfg.eval == cpu.eval  # its rows sit beside the cpu rows: the same drives


def test_flags_override_only_the_named_fields():
    cfg = _parse(
        "--config=tiny", "--data.image_size=64", "--model.conv_channels=4,8,16,32", "--model.variant=no_input_recon"
    )
    base = config_lib.get_config("tiny")
    assert cfg.data.image_size == 64 and cfg.model.conv_channels == (4, 8, 16, 32)
    assert cfg.model.variant == "no_input_recon"
    assert cfg.train == base.train and cfg.world == base.world and cfg.data.batch_size == base.data.batch_size


@pytest.mark.parametrize("name", sorted(config_lib.PRESETS))
def test_config_json_round_trips(name):
    cfg = config_lib.get_config(name)
    assert config_lib.Config.from_json(cfg.to_json()) == cfg


def test_the_defaults_are_the_recipe_every_training_preset_shares():
    """Config() trains what the presets train (the place stream, the belief head, the bird-eye grid, the
    decaying rate and the clip); only the tests' `tiny` keeps the reference's optimiser and fresh worlds."""
    default = config_lib.Config()
    recipe = lambda c: (
        c.model.pose_head,
        c.model.pose_hidden_dim,
        c.model.latent,
        c.data.place_frames,
        c.data.batches_per_drive,
    )
    optimiser = lambda c: dataclasses.replace(c.train, num_steps=0, checkpoint_every=0)
    for name in ("paper", "cpu", "demo"):
        cfg = config_lib.get_config(name)
        assert recipe(cfg) == recipe(default) and optimiser(cfg) == optimiser(default), name
    assert recipe(default) == ("belief", 512, "bev", 32, 10)


def test_a_run_saved_before_the_recipes_fields_reads_back_as_it_ran():
    """A config.json without the fields added since (today's defaults differ) gets what such runs ran with."""
    saved = json.loads(config_lib.get_config("cpu").to_json())
    for section, name in config_lib.SAVED_WITHOUT:
        del saved[section][name]
    del saved["model"]["detection_input"]
    cfg = config_lib.Config.from_dict(saved)
    assert (cfg.model.pose_head, cfg.model.pose_hidden_dim, cfg.model.latent) == ("regression", 0, "vector")
    assert (cfg.data.batches_per_drive, cfg.data.place_frames) == (1, 0)
    assert (cfg.train.lr_decay_share, cfg.train.max_grad_norm, cfg.train.pose_weight) == (0.0, 0.0, 1.0)
    assert cfg.model.detection_input == "latent" and cfg.model.feature_dim == 128  # saved fields kept


UNAWAITED_PROGRAM = """
import sys
from e2e_percep_jax import config
if sys.argv[1] == "after a failed restore":
    config.quieten_abandoned_reads("/run/checkpoints/2/default/")
async def read():
    pass
class Holder:
    pass
h = Holder()
h.coroutine, h.cycle = read(), h  # collected at exit, unawaited: it warns then
del h
"""


@pytest.mark.parametrize("failed_restore", [False, True])
def test_after_a_failed_restore_the_unawaited_reads_warn_no_more(failed_restore):
    """A failed restore leaves orbax's read coroutines to be collected unawaited at exit, each with a
    warning after the one error line: dropped once a restore failed, and only then."""
    argv = [sys.executable, "-c", UNAWAITED_PROGRAM, "after a failed restore" if failed_restore else "no restore"]
    err = subprocess.run(argv, capture_output=True, text=True, timeout=60).stderr
    assert ("coroutine 'read' was never awaited" in err) != failed_restore, err


@pytest.mark.parametrize(
    "name, allowed",
    [
        ("variant", config_lib.VARIANTS),
        ("pose_head", config_lib.POSE_HEADS),
        ("pose_filter", config_lib.POSE_FILTERS),
        ("detection_input", config_lib.DETECTION_INPUTS),
        ("latent", config_lib.LATENTS),
        ("grid_update", config_lib.GRID_UPDATES),
        ("lidar_decoder_input", config_lib.LIDAR_DECODER_INPUTS),
        ("grid_warp", config_lib.GRID_WARPS),
        ("grid_motion", config_lib.GRID_MOTIONS),
    ],
)
def test_each_choice_field_takes_its_choices_and_names_itself_otherwise(name, allowed):
    cfg = config_lib.replace(config_lib.get_config("tiny"), model=dict(latent="bev"))
    for value in allowed:  # a taught flow is taught by a weight of its own
        taught = dict(train=dict(flow_weight=1.0)) if value in config_lib.TAUGHT_FLOW_MOTIONS else {}
        config_lib.validate(config_lib.replace(cfg, model={name: value}, **taught))
    with pytest.raises(ValueError, match=rf"^--model\.{name}='nonsense': choose one of \("):
        config_lib.validate(config_lib.replace(cfg, model={name: "nonsense"}))
    if name.startswith("grid_"):  # the grid's own fields name the latent they need
        with pytest.raises(ValueError, match=rf"^--model\.{name}='{allowed[-1]}' .*: needs --model\.latent=bev$"):
            config_lib.validate(config_lib.replace(cfg, model={"latent": "vector", name: allowed[-1]}))


def test_the_flow_weight_needs_the_grids_scene_flow_and_is_never_negative():
    """--train.flow_weight teaches the flow that --model.grid_motion=ego_and_flow adds: without it (or
    without the grid) the flag names what it needs; a negative weight names itself; a flow taught by the moves
    alone (taught or carried) needs the weight."""
    tiny = config_lib.get_config("tiny")
    flow = config_lib.replace(tiny, model=dict(latent="bev", grid_motion="ego_and_flow"), train=dict(flow_weight=2.0))
    config_lib.validate(flow)
    for model in (dict(latent="bev"), dict(latent="vector")):
        with pytest.raises(
            ValueError,
            match=r"^--train\.flow_weight=2\.0 .*needs --model\.latent=bev and --model\.grid_motion one of \(",
        ):
            config_lib.validate(config_lib.replace(flow, model=dict(model, grid_motion="ego")))
    for name in ("flow_weight", "flow_vehicle_weight"):
        with pytest.raises(ValueError, match=rf"^--train\.{name}=-1\.0: must be at least 0$"):
            config_lib.validate(config_lib.replace(flow, train={name: -1.0}))
    for motion in config_lib.TAUGHT_FLOW_MOTIONS:
        taught = config_lib.replace(flow, model=dict(grid_motion=motion))
        config_lib.validate(taught)
        with pytest.raises(ValueError, match=rf"^--model\.grid_motion={motion} .*needs --train\.flow_weight > 0$"):
            config_lib.validate(config_lib.replace(taught, train=dict(flow_weight=0.0)))
