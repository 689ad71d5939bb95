"""Configs: presets are valid and hashable, flags override exactly the named field, config.json round-trips.
(Bad values, each naming its flag, are rows of test_bad_input.py.)"""

import dataclasses

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
