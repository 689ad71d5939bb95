"""Training tests: non-finite skipping and stopping, logs, launcher errors before compile, 4-device
equality, learning on real world batches, and kill-and-resume equivalence (subprocesses)."""
import dataclasses
import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest
from test_model import TINY, synthetic_batch

from e2e_percep_jax import train

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LAUNCHER = [sys.executable, os.path.join(ROOT, "experiments", "train.py")]


def tiny(**train_fields):
    return dataclasses.replace(TINY, train=dataclasses.replace(TINY.train, **train_fields))


CFG = tiny(num_steps=8, checkpoint_every=2, log_every=2, max_nonfinite_in_a_row=3)  # one compile for all


def synthetic_batches(nan_steps=(), stop=None):
    """A ``train.Batches`` of synthetic frames up to ``stop``; the pose is NaN at ``nan_steps``."""
    def stream(start):
        step = start
        while step != stop:
            batch = synthetic_batch(step, TINY)
            if step in nan_steps:
                batch["pose"] = np.full_like(batch["pose"], np.nan)
            yield step, batch
            step += 1
    return stream


def read_jsonl(path):
    with open(path) as f:
        return [json.loads(line) for line in f]


def saved_params(workdir, step):
    return ocp.StandardCheckpointer().restore(os.path.join(workdir, "checkpoints", str(step), "default"))["params"]


def assert_trees_equal(a, b):
    jax.tree.map(np.testing.assert_array_equal, a, b)


def run_python(code, **env):
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          env=dict(os.environ, PYTHONPATH=os.path.join(ROOT, "tests"), **env), timeout=600)


# ----------------------------------------------------------------------------- non-finite losses


def test_nonfinite_batch_skips_the_update():
    cfg = CFG
    mesh = train.make_mesh()
    step = train.make_train_step(cfg, mesh)
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    fresh = lambda: jax.device_put(train.init_state(cfg), replicated)  # a new one: the step donates its input
    before = jax.device_get(fresh())
    poisoned = dict(synthetic_batch(0, cfg), pose=np.full((2, 4, 5), np.nan, np.float32))
    state, metrics = step(fresh(), train.shard_batch(poisoned, mesh), jax.random.PRNGKey(0))
    assert not np.isfinite(metrics["total"])
    assert_trees_equal((state.params, state.opt_state), (before.params, before.opt_state))
    assert (int(state.step), int(state.nonfinite_in_a_row), int(state.nonfinite_total)) == (1, 1, 1)
    state, metrics = step(state, train.shard_batch(synthetic_batch(1, cfg), mesh), jax.random.PRNGKey(1))
    assert np.isfinite(metrics["total"])
    assert (int(state.step), int(state.nonfinite_in_a_row), int(state.nonfinite_total)) == (2, 0, 1)
    assert not np.array_equal(state.params["params"]["pose_head"]["Dense_2"]["bias"],
                              before.params["params"]["pose_head"]["Dense_2"]["bias"])


def test_stops_after_max_nonfinite_in_a_row_keeping_the_last_good_checkpoint(tmp_path):
    # Steps 0, 1 update; 2, 3, 4 are non-finite (the 3rd in a row halts updates), found at the log of step 6.
    with pytest.raises(train.NonFiniteLossError, match=r"stopping at step 6: 3 non-finite .*"
                                                       r"--train\.max_nonfinite_in_a_row=3.*step 4"):
        train.train(CFG, str(tmp_path), batches=synthetic_batches(nan_steps=range(2, 100)))
    assert checkpoint_steps(tmp_path) == [2, 4]
    assert_trees_equal(saved_params(tmp_path, 4), saved_params(tmp_path, 2))  # the skips changed nothing
    records = read_jsonl(tmp_path / "metrics.jsonl")
    assert [(r["nonfinite_in_a_row"], r["nonfinite_total"]) for r in records] == [(0, 0), (2, 2), (3, 4)]
    assert np.isfinite(records[0]["total"]) and not np.isfinite(records[1]["total"])


# ----------------------------------------------------------------------------- logs and resuming


def test_logs_metrics_progress_and_resumes(tmp_path, capsys):
    train.train(CFG, str(tmp_path), batches=synthetic_batches(stop=4))  # data ends: checkpoint at exit
    records = read_jsonl(tmp_path / "metrics.jsonl")
    assert [r["step"] for r in records] == [2, 4]
    assert set(records[0]) >= {"recon_camera", "recon_lidar", "recon_roadmap", "kl", "det_cls", "det_reg", "pose",
                               "total", "grad_norm", "steps_per_s", "nonfinite_total"}
    out = capsys.readouterr().out
    assert "step 4/8" in out and "steps/s" in out and "ETA" in out
    assert json.loads((tmp_path / "config.json").read_text())["train"]["num_steps"] == 8
    assert checkpoint_steps(tmp_path) == [2, 4]

    state = train.train(CFG, str(tmp_path), batches=synthetic_batches())
    assert "resumed from step 4" in capsys.readouterr().out
    assert int(state.step) == 8
    assert [r["step"] for r in read_jsonl(tmp_path / "metrics.jsonl")] == [2, 4, 6, 8]
    assert checkpoint_steps(tmp_path) == [4, 6, 8]  # the last MAX_CHECKPOINTS_KEPT


# ----------------------------------------------------------------------------- launcher errors


@pytest.mark.parametrize("flag, named", [("--data.image_size=48", "--data.image_size=48"),
                                         ("--data.image_size=abc", "--data.image_size"),
                                         ("--model.variant=both", "--model.variant"),
                                         ("--model.conv_channels=8,x", "--model.conv_channels"),
                                         ("--train.learning_rate=0", "--train.learning_rate"),
                                         ("--data.nonsense=1", "data.nonsense")])
def test_launcher_bad_flag_is_one_line_before_any_compile(tmp_path, flag, named):
    workdir = tmp_path / "run"
    r = subprocess.run(LAUNCHER + ["--config=tiny", f"--workdir={workdir}", flag], capture_output=True, text=True,
                       env=dict(os.environ, JAX_LOG_COMPILES="1"), timeout=120)
    assert r.returncode != 0
    assert r.stderr.strip().count("\n") == 0 and r.stderr.startswith("error: ") and named in r.stderr, r.stderr
    assert not workdir.exists()


def test_launcher_rejects_batch_not_divisible_by_devices_and_config_changes_before_compile(tmp_path):
    four_devices = dict(os.environ, JAX_LOG_COMPILES="1", XLA_FLAGS="--xla_force_host_platform_device_count=4")
    r = subprocess.run(LAUNCHER + ["--config=tiny", f"--workdir={tmp_path}", "--data.batch_size=3"],
                       capture_output=True, text=True, env=four_devices, timeout=120)
    assert r.returncode != 0 and r.stderr.count("\n") == 1 and "--data.batch_size=3" in r.stderr, r.stderr

    train.train(CFG, str(tmp_path), batches=synthetic_batches(stop=1))
    r = subprocess.run(LAUNCHER + ["--config=tiny", f"--workdir={tmp_path}", "--model.z1_dim=4"],
                       capture_output=True, text=True, env=dict(os.environ, JAX_LOG_COMPILES="1"), timeout=120)
    assert r.returncode != 0 and r.stderr.count("\n") == 1 and "--model.z1_dim=4 differs" in r.stderr, r.stderr


# ----------------------------------------------------------------------------- data parallel


@pytest.mark.slow
def test_four_devices_equal_one_device():
    """Loss, gradients and a train step with the batch sharded over 4 CPU devices equal 1 device."""
    r = run_python("""
        import dataclasses, jax, numpy as np
        from jax.sharding import NamedSharding, PartitionSpec
        from test_model import TINY, synthetic_batch
        from e2e_percep_jax import loss, train
        assert jax.device_count() == 4
        cfg = dataclasses.replace(TINY, data=dataclasses.replace(TINY.data, batch_size=4))
        batch, key = synthetic_batch(0, cfg), jax.random.PRNGKey(7)
        grad_fn = jax.jit(jax.value_and_grad(lambda p, b, k: loss.loss_fn(p, b, k, cfg), has_aux=True))
        results = []
        for mesh in (train.make_mesh(jax.devices()[:1]), train.make_mesh()):
            sharded = train.shard_batch(batch, mesh)
            assert sharded["camera"].sharding.shard_shape(sharded["camera"].shape)[0] == 4 // mesh.size
            state = jax.device_put(train.init_state(cfg), NamedSharding(mesh, PartitionSpec()))
            (total, metrics), grads = grad_fn(state.params, sharded, key)
            step = train.make_train_step(cfg, mesh)
            for i in range(2):
                state, _ = step(state, sharded, jax.random.fold_in(key, i))
            results.append(jax.device_get((metrics, grads, state.params)))
        (m1, g1, p1), (m4, g4, p4) = results
        for k in m1:
            np.testing.assert_allclose(m4[k], m1[k], rtol=1e-5, err_msg=k)
        # float32 sums in another order: compare each gradient to its own largest magnitude
        jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * np.abs(b).max()), g4, g1)
        # Adam moves each parameter ~learning_rate a step whatever the gradient's size: 5% of one step
        jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=0, atol=0.05 * cfg.train.learning_rate), p4, p1)
        assert not np.allclose(p1["params"]["pose_head"]["Dense_2"]["bias"],
                               jax.device_get(train.init_state(cfg).params)["params"]["pose_head"]["Dense_2"]["bias"])
        print("ok")
        """, XLA_FLAGS="--xla_force_host_platform_device_count=4")
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stdout + r.stderr


# ----------------------------------------------------------------------------- real world batches


@pytest.mark.slow
def test_tiny_run_on_world_batches_lowers_every_loss_term(tmp_path):
    """600 steps of the tiny model on the world's batches. 100 vehicles so that the 32 m view often holds
    one (det_reg is non-zero only then); learning rate 1e-3 so the KL is past its rise within the run (at
    initialisation q and p are alike, the KL is small; it peaks once the posterior encodes the frames)."""
    cfg = tiny(num_steps=600, log_every=1, checkpoint_every=600, learning_rate=1e-3)
    cfg = dataclasses.replace(cfg, world=dataclasses.replace(cfg.world, num_vehicles=100))
    train.train(cfg, str(tmp_path))
    records = read_jsonl(tmp_path / "metrics.jsonl")
    terms = [k for k in records[0] if k.startswith("recon_") or k in ("kl", "det_cls", "det_reg", "pose")]
    assert len(terms) == 7
    first, last = records[:20], records[-20:]
    for k in terms:
        start, end = np.mean([r[k] for r in first]), np.mean([r[k] for r in last])
        assert end < start, f"{k}: mean of the first 20 steps {start:.4g}, of the last 20 {end:.4g}"


STEPS = 60  # enough for the signals to land mid-run


def launch(workdir, cache):
    """The launcher on the tiny config; compilations are shared through a persistent cache (speed only)."""
    return subprocess.Popen(LAUNCHER + ["--config=tiny", f"--workdir={workdir}", f"--train.num_steps={STEPS}",
                                        "--train.checkpoint_every=5", "--train.log_every=5"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, JAX_COMPILATION_CACHE_DIR=str(cache)))


def checkpoint_steps(workdir):
    """Finished checkpoints (orbax writes into a temporary name and renames it to the step when done)."""
    path = os.path.join(workdir, "checkpoints")
    return sorted(int(d) for d in os.listdir(path) if d.isdigit()) if os.path.isdir(path) else []


def wait_for_checkpoint(proc, workdir, after):
    """Waits until ``workdir`` has a finished checkpoint later than ``after``, the run still going."""
    deadline = time.time() + 300
    while time.time() < deadline:
        if checkpoint_steps(workdir) and checkpoint_steps(workdir)[-1] > after:
            return
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    raise TimeoutError


@pytest.mark.slow
def test_sigterm_then_sigkill_then_resume_equals_an_uninterrupted_run(tmp_path):
    whole, cut, cache = str(tmp_path / "whole"), str(tmp_path / "cut"), tmp_path / "cache"
    proc = launch(whole, cache)
    assert proc.wait(timeout=600) == 0, proc.communicate()

    proc = launch(cut, cache)
    wait_for_checkpoint(proc, cut, after=0)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM and "SIGTERM" in err, out + err
    stopped = checkpoint_steps(cut)[-1]

    proc = launch(cut, cache)
    wait_for_checkpoint(proc, cut, after=stopped)
    proc.kill()  # SIGKILL: no chance to save anything
    assert proc.wait() == -signal.SIGKILL
    killed_at = checkpoint_steps(cut)[-1]
    assert killed_at < STEPS

    proc = launch(cut, cache)
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0 and f"resumed from step {killed_at}" in out, out + err
    assert_trees_equal(saved_params(cut, STEPS), saved_params(whole, STEPS))
    losses = lambda d: [(r["step"], r["total"], r["kl"]) for r in read_jsonl(os.path.join(d, "metrics.jsonl"))]
    assert losses(cut) == losses(whole) and len(losses(whole)) == STEPS // 5
