"""allocator.keep_freed_buffers: counted page faults, in a fresh process (the setting is process-wide)."""

import ctypes.util
import os
import subprocess
import sys

import pytest

from e2e_percep_jax import allocator

_FAULTS_PER_CYCLE = """
import resource, numpy as np
from e2e_percep_jax import allocator
def faults(n_bytes=48 << 20, cycles=4):  # above glibc's largest dynamic mmap threshold (32 MiB)
    np.ones(n_bytes, np.uint8)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(cycles):
        np.ones(n_bytes, np.uint8)  # written in full: every page it gets fresh is faulted in
    return (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / cycles
before = faults()
applied = allocator.keep_freed_buffers()
print(before, applied, faults())
"""


@pytest.mark.skipif(
    not sys.platform.startswith("linux") or "libc.so.6" not in str(ctypes.util.find_library("c")), reason="glibc only"
)
def test_freed_buffers_are_reused_without_new_page_faults():
    out = subprocess.run(
        [sys.executable, "-c", _FAULTS_PER_CYCLE],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "GLIBC_TUNABLES": ""},
    ).stdout.split()
    before, applied, after = float(out[0]), out[1], float(out[2])
    # 48 MiB in pages of at most 2 MiB (transparent huge pages): >= 24 faults a cycle while each buffer is
    # mapped afresh; none once freed buffers are kept.
    assert before >= 24, before
    assert applied == "True"
    assert after <= 1, after


def test_bad_thresholds_are_refused_by_name():
    with pytest.raises(ValueError, match="mmap_threshold_mib=0"):
        allocator.keep_freed_buffers(mmap_threshold_mib=0)
    with pytest.raises(ValueError, match="trim_threshold_mib=8"):
        allocator.keep_freed_buffers(mmap_threshold_mib=16, trim_threshold_mib=8)
