"""Multi-process data parallelism: two processes joined by ``jax.distributed`` train as one.

The launcher runs as processes 0 and 1 of one run (``--coordinator_address`` on localhost, one CPU device
each, so the global batch of 2 is one row per process), while the same config trains in this process on
its one device. Both see the same global batches and the same latent noise, so they take the same Adam
steps up to float32 rounding. The two-process run is stopped by SIGTERM to process 0 alone.
"""

import concurrent.futures
import json
import os
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest
from helpers import LAUNCHER, TINY_FLAGS, checkpoint_steps, free_port, read_jsonl, tiny, xla_flags

from e2e_percep_jax import train

STEPS = 20  # the two-process run stops long before (it is sent SIGTERM after its first checkpoint)
CHECKPOINT_EVERY = 2
CFG = tiny(num_steps=STEPS, checkpoint_every=CHECKPOINT_EVERY, log_every=1)
FLAGS = TINY_FLAGS + [
    f"--train.num_steps={STEPS}",
    f"--train.checkpoint_every={CHECKPOINT_EVERY}",
    "--train.log_every=1",
    "--num_processes=2",
]
# Adam moves every parameter by about the learning rate per step, whatever its gradient's size. Summing the
# gradient over two processes' rows instead of over one device's changes it by float32 rounding (~1e-7
# relative), which moves the parameters by ~1e-6 (3e-6 measured after 3 and after 8 steps); a wrong or
# missing row, or a gradient not summed over the processes, points Adam's steps elsewhere: O(learning rate) =
# 1e-3 each. So the parameters must agree to a tenth of one step's move.
PARAMS_ATOL = 0.1 * CFG.train.learning_rate
# The logged loss terms: the same sums in another order, on parameters that differ by rounding.
METRICS_RTOL = 1e-5

# The launcher as ``__main__``, as ``python experiments/train.py`` runs it, then one line with what JAX saw
# in that process: proof that ``jax.distributed.initialize`` joined the processes.
WITH_PROCESS_COUNT = """
import runpy, sys, jax
sys.argv = sys.argv[1:]
try:
    runpy.run_path(sys.argv[0], run_name="__main__")
finally:
    print(f"process {jax.process_index()} of {jax.process_count()}, {jax.device_count()} devices", flush=True)
"""


def launch_two_processes(workdir):
    """Processes 0 and 1 of one launcher run in ``workdir``; their Popen objects."""
    flags = FLAGS + [f"--workdir={workdir}", f"--coordinator_address=localhost:{free_port()}"]
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=xla_flags("--xla_force_host_platform_device_count=1"))
    return [
        subprocess.Popen(
            [sys.executable, "-c", WITH_PROCESS_COUNT] + LAUNCHER[1:] + flags + [f"--process_id={i}"],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        for i in range(2)
    ]


def stop_all(procs):
    """Kills those of ``procs`` still running; everything they printed, for a failure message."""
    for p in procs:
        if p.poll() is None:
            p.kill()
    return "\n".join(f"--- process {i} (exit status {p.wait()}):\n{p.communicate()[0]}" for i, p in enumerate(procs))


def wait_for_both(procs, status, timeout=600):
    """The processes' outputs once both have exited, each with ``status``. One that exits otherwise would
    leave the other waiting minutes at the coordinator's barriers, so the other is stopped at once; so is
    everything past ``timeout`` (a hang)."""
    deadline = time.time() + timeout
    while any(p.poll() is None for p in procs):
        if time.time() > deadline or any(p.poll() not in (None, status) for p in procs):
            raise AssertionError(f"expected both to exit with status {status}\n{stop_all(procs)}")
        time.sleep(0.2)
    outputs = [p.communicate()[0] for p in procs]
    assert all(p.returncode == status for p in procs), outputs
    return outputs


def wait_for_checkpoint(procs, workdir, timeout=600):
    """Waits until ``workdir`` has a finished checkpoint, both processes still running."""
    deadline = time.time() + timeout
    while not checkpoint_steps(workdir):
        if time.time() > deadline or any(p.poll() is not None for p in procs):
            raise AssertionError(f"no checkpoint in {workdir} while both ran\n{stop_all(procs)}")
        time.sleep(0.02)


def restore_params(workdir, step):
    """The params of checkpoint ``step`` on this process's one device (a checkpoint written by two processes
    names their two devices, so it is restored into an explicit target)."""
    device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    target = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=device), train.init_state(CFG))
    path = os.path.join(workdir, "checkpoints", str(step), "default")
    with ocp.StandardCheckpointer() as checkpointer:
        return jax.device_get(checkpointer.restore(path, target).params)


@pytest.mark.slow
def test_two_processes_train_as_one_and_stop_together(tmp_path):
    """Two launcher processes joined by jax.distributed (one device each) train as one process on one device
    does: the same parameters and logged losses, one metrics record per step. SIGTERM to process 0 alone
    stops both after the same step, with its checkpoint."""
    two, one = tmp_path / "two", tmp_path / "one"
    procs = launch_two_processes(two)
    try:
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            reference = pool.submit(train.train, CFG, str(one))  # in this process while the two compile
            wait_for_checkpoint(procs, two)
            procs[0].send_signal(signal.SIGTERM)
            outputs = wait_for_both(procs, 128 + signal.SIGTERM, timeout=300)
            reference.result()
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    stopped_at = checkpoint_steps(two)[-1]
    assert CHECKPOINT_EVERY <= stopped_at < STEPS, outputs
    for i, out in enumerate(outputs):
        assert f"process {i} of 2, 2 devices" in out, out
        assert f"interrupted by SIGTERM at step {stopped_at}; checkpoint saved" in out, out
    # Process 0 alone logs and writes the run's files.
    assert f"step {stopped_at}/{STEPS}" in outputs[0] and f"step {stopped_at}/{STEPS}" not in outputs[1], outputs
    assert json.loads((two / "config.json").read_text()) == json.loads((one / "config.json").read_text())
    records, expected_records = read_jsonl(two / "metrics.jsonl"), read_jsonl(one / "metrics.jsonl")[:stopped_at]
    assert [r["step"] for r in records] == [r["step"] for r in expected_records] == list(range(1, stopped_at + 1))
    for r, e in zip(records, expected_records):
        for k in set(e) - {"steps_per_s"}:
            np.testing.assert_allclose(r[k], e[k], rtol=METRICS_RTOL, err_msg=f"step {e['step']}: {k}")

    # The single-process run's parameters at that step (the same compiled step and batches: seconds).
    expected = jax.device_get(
        train.train(
            tiny(num_steps=stopped_at, checkpoint_every=CHECKPOINT_EVERY, log_every=1), str(tmp_path / "one_to_stop")
        ).params
    )
    params, init = restore_params(two, stopped_at), jax.device_get(train.init_state(CFG).params)
    assert jax.tree.structure(params) == jax.tree.structure(expected)

    def check(path, got, want, start):
        name = jax.tree_util.keystr(path)
        assert np.max(np.abs(want - start)) > 10 * PARAMS_ATOL, f"{name} did not train"
        np.testing.assert_allclose(got, want, rtol=0, atol=PARAMS_ATOL, err_msg=name)

    jax.tree.map_with_path(check, params, expected, init)
