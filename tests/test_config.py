"""Configs: presets are valid and hashable, flags override exactly the named field, bad values name their flag."""
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


def test_paper_preset_is_the_papers_network():
    cfg = config_lib.get_config("paper")
    assert (cfg.data.image_size, cfg.data.seq_len) == (128, 10)
    assert cfg.model.conv_channels[:5] == (32, 64, 128, 256, 256)
    assert (cfg.model.z1_dim, cfg.model.z2_dim, cfg.train.learning_rate) == (32, 256, 1e-4)


def test_flags_override_only_the_named_fields():
    cfg = _parse("--config=tiny", "--data.image_size=64", "--model.conv_channels=4,8,16,32", "--model.variant=no_input_recon")
    base = config_lib.get_config("tiny")
    assert cfg.data.image_size == 64 and cfg.model.conv_channels == (4, 8, 16, 32)
    assert cfg.model.variant == "no_input_recon"
    assert cfg.train == base.train and cfg.world == base.world and cfg.data.batch_size == base.data.batch_size


@pytest.mark.parametrize("argv, flag", [
    (["--data.image_size=48"], "--data.image_size"),
    (["--data.image_size=16"], "--data.image_size"),
    (["--data.batch_size=0"], "--data.batch_size"),
    (["--model.variant=bogus"], "--model.variant"),
    (["--model.conv_channels=8,-16,32"], "--model.conv_channels[1]"),
    (["--model.conv_channels=8,x"], "--model.conv_channels"),
    (["--data.image_size=256"], "--model.conv_channels"),  # tiny has 3 widths; R = 256 needs 6
    (["--eval.score_threshold=1.5"], "--eval.score_threshold"),
    (["--data.warmup_steps=-1"], "--data.warmup_steps"),
    (["--data.batches_per_drive=0"], "--data.batches_per_drive"),
    (["--train.max_grad_norm=-1"], "--train.max_grad_norm"),
    (["--train.pose_weight=-1"], "--train.pose_weight"),
    (["--train.kl_weight=0"], "--train.kl_weight"),
    (["--model.pose_filter=kalman"], "--model.pose_filter"),
    (["--data.carry_state"], "--data.carry_state"),  # tiny has one batch per drive: nothing to carry across
    (["--eval.known_start", "--model.pose_filter=none"], "--eval.known_start"),
])
def test_bad_values_name_their_flag(argv, flag):
    with pytest.raises(ValueError) as err:
        _parse("--config=tiny", *argv)
    message = str(err.value)
    assert message.startswith(flag) and "\n" not in message


def test_unknown_preset_is_named():
    with pytest.raises(ValueError, match="--config='nope'"):
        _parse("--config=nope")


@pytest.mark.parametrize("name", sorted(config_lib.PRESETS))
def test_config_json_round_trips(name):
    cfg = config_lib.get_config(name)
    assert config_lib.Config.from_json(cfg.to_json()) == cfg


def test_config_json_with_unknown_field_is_refused():
    with pytest.raises(ValueError, match="unknown fields"):
        config_lib.Config.from_json('{"data": {"image_sise": 64}}')
