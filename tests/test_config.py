"""Configs: presets are valid and hashable, flags override exactly the named field, config.json round-trips.
(Bad values, each naming its flag, are rows of test_bad_input.py.)"""

import dataclasses
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


QUIET_PROGRAM = """
import asyncio, logging, sys
from e2e_percep_jax import config
if sys.argv[1] == "quiet":
    config.quieten_abandoned_reads("/run/checkpoints/2/default/")
logging.basicConfig(format="%(message)s")
logging.getLogger("asyncio").error("Future exception was never retrieved: reading /run/checkpoints/2/default/")
logging.getLogger("asyncio").error("Task exception was never retrieved: something else")
async def read():
    pass
class Holder:
    pass
h = Holder()
h.coroutine, h.cycle = read(), h  # collected at exit, unawaited: it warns then
del h
"""


@pytest.mark.parametrize("quiet", [False, True])
def test_a_failed_restores_abandoned_reads_are_dropped_and_nothing_else(quiet):
    """After a checkpoint's restore failed, asyncio's reports naming it and the warnings of coroutines
    collected unawaited are dropped; another report stays. Without the call, all three print."""
    argv = [sys.executable, "-c", QUIET_PROGRAM, "quiet" if quiet else "loud"]
    err = subprocess.run(argv, capture_output=True, text=True, timeout=60).stderr
    assert "something else" in err
    assert ("reading /run/checkpoints/2/default/" in err) != quiet, err
    assert ("was never awaited" in err) != quiet, err
