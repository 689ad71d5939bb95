"""xla_cpu.prefer_eigen_convolutions: which path convolutions take, in fresh processes (XLA reads its
flags once, at start-up), and that a choice already made is never overridden."""

import os
import subprocess
import sys

import numpy as np
import pytest

from e2e_percep_jax import xla_cpu

_CONV_GRADIENT = """
import sys
import jax, jax.numpy as jnp, numpy as np
from e2e_percep_jax import xla_cpu
preferred = xla_cpu.prefer_eigen_convolutions() if sys.argv[1] == "prefer" else None
x = jax.random.normal(jax.random.PRNGKey(0), (8, 32, 32, 32))
w = jax.random.normal(jax.random.PRNGKey(1), (3, 3, 32, 64)) / 17.0
conv = lambda x, w: jax.lax.conv_general_dilated(x, w, (2, 2), ((1, 1), (1, 1)), dimension_numbers=("NHWC", "HWIO", "NHWC"))
y, (gx, gw) = jax.jit(lambda x, w: (conv(x, w), jax.grad(lambda x, w: jnp.sum(conv(x, w) ** 2), (0, 1))(x, w)))(x, w)
np.savez(sys.argv[2], y=y, gx=gx, gw=gw)
print(preferred, xla_cpu.convolution_path())
"""


def _run(mode, out_path):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_PLATFORMS")}
    out = subprocess.run(
        [sys.executable, "-c", _CONV_GRADIENT, mode, out_path], capture_output=True, text=True, check=True, env=env
    ).stdout.split()
    return out, np.load(out_path)


@pytest.mark.skipif(not xla_cpu.jaxlib_measured(), reason="jaxlib outside the measured range: XLA's default is kept")
def test_convolutions_move_to_eigen_and_only_rounding_changes(tmp_path):
    (preferred, path), eigen = _run("prefer", str(tmp_path / "eigen.npz"))
    assert (preferred, path) == ("True", "eigen")
    (_, path), default = _run("default", str(tmp_path / "default.npz"))
    assert path == "ynn"
    for name in ("y", "gx", "gw"):
        scale = np.abs(default[name]).max()
        assert np.abs(eigen[name] - default[name]).max() <= 1e-5 * scale, name


def test_a_choice_already_made_is_kept(monkeypatch):
    users = "--xla_cpu_experimental_ynn_fusion_type=+individual_convolution --xla_force_host_platform_device_count=2"
    monkeypatch.setenv("XLA_FLAGS", users)
    assert xla_cpu.prefer_eigen_convolutions() is False
    assert os.environ["XLA_FLAGS"] == users


def test_other_platforms_and_unmeasured_jaxlib_are_left_alone(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    monkeypatch.setenv("JAX_PLATFORMS", "cuda")
    assert xla_cpu.prefer_eigen_convolutions() is False
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    monkeypatch.setattr(xla_cpu, "MEASURED_JAXLIB", ((0, 0), (0, 1)))
    assert xla_cpu.prefer_eigen_convolutions() is False
    assert os.environ["XLA_FLAGS"] == "--xla_force_host_platform_device_count=2"
    monkeypatch.setattr(xla_cpu, "MEASURED_JAXLIB", ((0, 0), (99, 0)))
    assert xla_cpu.prefer_eigen_convolutions() is True
    assert os.environ["XLA_FLAGS"] == (
        "--xla_force_host_platform_device_count=2 --xla_cpu_experimental_ynn_fusion_type=-individual_convolution"
    )
