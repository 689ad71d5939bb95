"""Fixtures for every test module. Plain helpers that test modules import are in helpers.py."""

import atexit
import gc
import os
import shutil
import tempfile

# One persistent compilation cache for the whole suite, this process and the launchers it starts (they inherit
# the environment): most launcher tests compile the same `tiny` programs (the calibration's drive, the train
# step, the evaluation), and a cache hit loads them instead of compiling again. Set before jax is imported,
# which reads it then; a cache the caller names is kept.
# The same for the towns that every launcher process would otherwise build again with NumPy (seconds each).
for variable, prefix in (
    ("JAX_COMPILATION_CACHE_DIR", "e2e-percep-jax-cache-"),
    ("E2E_PERCEP_JAX_TOWN_CACHE", "e2e-percep-jax-towns-"),
):
    if variable not in os.environ:
        os.environ[variable] = tempfile.mkdtemp(prefix=prefix)
        atexit.register(shutil.rmtree, os.environ[variable], True)

import helpers  # noqa: E402  (imports jax: after the cache is named; XLA reads its flags at the first computation)

# The suite compiles hundreds of small programs that then run for moments, so XLA's LLVM optimisation of
# them costs more than it saves: it is off for the suite and the launchers it starts (a third less CPU in
# the fast tier). Rounding moves (no fused multiply-adds), so a test that compares with numbers recorded
# at the default level compiles that program at the default level (`helpers.OPTIMISED`).
if helpers.OPTIMISATION_FLAG not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {helpers.OPTIMISATION_FLAG}=0".strip()

import jax  # noqa: E402
import pytest  # noqa: E402

from e2e_percep_jax import config, xla_cpu  # noqa: E402
from e2e_percep_jax.sim import town as town_lib  # noqa: E402

# The convolution path the launchers and e2e.load choose, set before any test computes (process-wide;
# the launchers that tests start inherit it).
xla_cpu.prefer_eigen_convolutions()


@pytest.fixture(scope="module", autouse=True)
def start_first(request):
    """Sets up, before the first test of a module, the module-scoped fixtures that the module names in
    ``START_FIRST``: work started in the background (subprocess runs) that overlaps the module's other tests.
    Only those that a test selected to run uses: under ``-m "not slow"`` a background run that only slow
    tests read is never started, nor waited for."""
    selected = [item for item in request.session.items if getattr(item, "module", None) is request.module]
    for name in getattr(request.module, "START_FIRST", ()):
        if any(name in item.fixturenames for item in selected):
            request.getfixturevalue(name)


@pytest.fixture(scope="module", autouse=True)
def release_compiled_programs():
    """Drops every compiled program after a module's tests. XLA:CPU maps each program's code into memory
    in pieces (~1,850 maps for one `make_batch` of the tiny config, at any optimisation level), a worker
    that keeps them all for its share of the suite passes Linux's 65,530 maps a process
    (`vm.max_map_count`), and the next compile then dies inside LLVM with a segfault. A program that a
    later module needs again compiles again, or loads from the persistent compilation cache if it took
    long enough to compile to be kept there."""
    yield
    jax.clear_caches()
    gc.collect()


@pytest.fixture(scope="session", autouse=True)
def warm_town_cache():
    """The ``tiny`` config's town built before a worker's first test, so that the launchers that tests
    start (a module's fixtures start some at once) find it in the suite's town cache."""
    town_lib.build_town(config.get_config("tiny").world.town_seed)


@pytest.fixture(scope="session")
def town():
    """The ``tiny`` config's town, for the modules that drive it (a module may define its own ``town``)."""
    return town_lib.build_town(config.get_config("tiny").world.town_seed)
