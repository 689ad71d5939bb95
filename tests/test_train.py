"""Training tests: non-finite skipping and stopping, logs, launcher errors before compile with a
coordinator (the other launcher errors are rows of test_bad_input.py), 4-device equality, learning on real
world batches, and SIGKILL- and SIGTERM-and-resume equivalence.

Every in-process run shares ONE train-step compilation (runs differing only in num_steps, log_every and
checkpoint_every compile the same step, see ``train.step_config``), and the subprocesses share a
persistent compilation cache.
"""

import concurrent.futures
import itertools
import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import jax
import numpy as np
import optax
import orbax.checkpoint as ocp
import pytest
from helpers import (
    LAUNCHER,
    ROOT,
    TINY,
    TINY_FLAGS,
    checkpoint_steps,
    environment,
    free_port,
    loss_and_grads,
    read_jsonl,
    synthetic_batch,
    tiny,
    xla_flags,
)

from e2e_percep_jax import checkpoint, config, loss, model, train, train_state

CFG = tiny(num_steps=8, checkpoint_every=2, log_every=2)
POSE_TERMS = ("pose_place", "pose_heading", "pose_offset", "pose_speed")  # the belief head's loss terms
START_FIRST = ["subprocess_runs"]  # see conftest.start_first


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


def saved_params(workdir, step):
    return ocp.StandardCheckpointer().restore(os.path.join(workdir, "checkpoints", str(step), "default"))["params"]


def assert_trees_equal(a, b):
    jax.tree.map(np.testing.assert_array_equal, a, b)


def run_python(code, env):
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        env=dict(env, PYTHONPATH=os.path.join(ROOT, "tests")),
        timeout=600,
    )


def four_device_loss_and_grads(workdir, env):
    """(metrics, gradients) of the B = 4 synthetic batch sharded over 4 simulated CPU devices. ``env``: this
    process's environment, as ``helpers.environment`` copies it in the main thread."""
    path = workdir / "four.pkl"
    r = run_python(
        f"""
        import pickle, jax
        from jax.sharding import NamedSharding, PartitionSpec
        from helpers import TINY, loss_and_grads, synthetic_batch
        from e2e_percep_jax import model, train
        assert jax.device_count() == 4
        mesh = train.make_mesh()
        batch = train.shard_batch(synthetic_batch(0, TINY, batch_size=4), mesh, TINY)
        assert batch["camera"].sharding.shard_shape(batch["camera"].shape)[0] == 1
        params = jax.device_put(model.init_params(jax.random.PRNGKey(0), TINY), NamedSharding(mesh, PartitionSpec()))
        (_, metrics), grads = loss_and_grads(params, batch, jax.random.PRNGKey(7), TINY)
        with open({str(path)!r}, "wb") as f:
            pickle.dump(jax.device_get((metrics, grads)), f)
        """,
        dict(env, XLA_FLAGS=xla_flags("--xla_force_host_platform_device_count=4", env=env)),
    )
    assert r.returncode == 0, r.stdout + r.stderr
    with open(path, "rb") as f:
        return pickle.load(f)


@pytest.fixture(scope="module")
def subprocess_runs(tmp_path_factory):
    """The subprocess runs, started before the first test of this file (``START_FIRST``): XLA compiles on one
    core, so on this 2-core machine they overlap with the in-process tests. Futures of their results; the
    threads get the environment as ``helpers.environment`` copies it here, in the main thread."""
    env = environment()
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        yield {
            "four_devices": pool.submit(four_device_loss_and_grads, tmp_path_factory.mktemp("four"), env),
            "stops": pool.submit(stops_and_resumes, tmp_path_factory.mktemp("stops"), env),
        }


# ----------------------------------------------------------------------------- non-finite losses


@pytest.mark.slow
def test_nonfinite_batch_skips_the_update():
    cfg = CFG
    mesh = train.make_mesh()
    step = train.make_train_step(cfg, mesh)
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    fresh = lambda: jax.device_put(train.init_state(cfg), replicated)  # a new one: the step donates its input
    before = jax.device_get(fresh())
    poisoned = dict(synthetic_batch(0, cfg), pose=np.full((2, 4, 5), np.nan, np.float32))
    state, metrics = step(fresh(), train.shard_batch(poisoned, mesh, cfg), jax.random.PRNGKey(0))
    assert not np.isfinite(metrics["total"])
    assert_trees_equal((state.params, state.opt_state), (before.params, before.opt_state))
    assert (int(state.step), int(state.nonfinite_in_a_row), int(state.nonfinite_total)) == (1, 1, 1)
    state, metrics = step(state, train.shard_batch(synthetic_batch(1, cfg), mesh, cfg), jax.random.PRNGKey(1))
    assert np.isfinite(metrics["total"])
    assert (int(state.step), int(state.nonfinite_in_a_row), int(state.nonfinite_total)) == (2, 0, 1)
    assert not np.array_equal(
        state.params["params"]["pose_belief_head"]["Dense_2"]["bias"],
        before.params["params"]["pose_belief_head"]["Dense_2"]["bias"],
    )


@pytest.mark.slow
def test_compiled_step_uses_the_perception_pose_and_kl_weights():
    """``train.perception_weight``, ``train.pose_weight`` and ``train.kl_weight`` reach the jitted step (its
    config is trimmed for compile reuse). All three changed at once (two compilations, not four), each term
    shows its own: perception weight 1 against the default 32 divides the detection terms by 32, the pose
    terms (perception x pose weight) go from 32 x 1 to 1 x 5, KL weight 0.25 scales the KL alone, and the
    reconstructions keep their value."""
    mesh = train.make_mesh()
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    batch = train.shard_batch(synthetic_batch(0, CFG), mesh, CFG)
    w = CFG.train.perception_weight
    assert (w, CFG.train.pose_weight, CFG.train.kl_weight) == (32.0, 1.0, 1.0)
    base, changed = (
        train.make_train_step(cfg, mesh)(
            jax.device_put(train.init_state(cfg), replicated), batch, jax.random.PRNGKey(0)
        )[1]
        for cfg in (CFG, config.replace(CFG, train=dict(perception_weight=1.0, pose_weight=5.0, kl_weight=0.25)))
    )
    for k in ("det_cls", "det_reg"):
        np.testing.assert_allclose(changed[k], base[k] / w, rtol=1e-5, err_msg=k)
    for k in POSE_TERMS:
        np.testing.assert_allclose(changed[k], 5.0 * base[k] / w, rtol=1e-5, err_msg=k)
    np.testing.assert_allclose(changed["kl"], 0.25 * base["kl"], rtol=1e-5)
    for k in ("recon_camera", "recon_lidar", "recon_roadmap"):
        np.testing.assert_allclose(changed[k], base[k], rtol=1e-6, err_msg=k)
    not_terms = ("total", "grad_norm", "nonfinite_in_a_row", "nonfinite_total")
    for m in (base, changed):  # the objective is the plain sum of the weighted terms
        np.testing.assert_allclose(m["total"], sum(v for k, v in m.items() if k not in not_terms), rtol=1e-6)


def test_gradient_clip_is_adam_on_the_rescaled_gradient():
    """--train.max_grad_norm=c: a gradient of norm n > c updates as plain Adam on gradient * c / n, one
    within c as plain Adam on itself; c = 0 is plain Adam with its state's structure (older runs restore)."""
    params = {"a": np.ones(3, np.float32), "b": np.ones((2, 2), np.float32)}
    direction = {"a": np.array([3.0, 0.0, -4.0], np.float32), "b": np.zeros((2, 2), np.float32)}  # norm 5
    clip, lr = 10.0, 1e-3
    clipped = train.optimizer(config.replace(CFG, train=dict(learning_rate=lr, max_grad_norm=clip)))
    adam = train.optimizer(config.replace(CFG, train=dict(learning_rate=lr, max_grad_norm=0.0)))
    assert jax.tree.structure(adam.init(params)) == jax.tree.structure(optax.adam(lr).init(params))
    for scale, expected_scale in ((1e12, clip / 5.0), (1.0, 1.0)):  # norms 5e12 (clipped) and 5 (not)
        grads = jax.tree.map(lambda d: d * scale, direction)
        got, _ = clipped.update(grads, clipped.init(params), params)
        want, _ = adam.update(jax.tree.map(lambda d: d * expected_scale, direction), adam.init(params), params)
        jax.tree.map(lambda g, w: np.testing.assert_allclose(g, w, rtol=1e-6), got, want)
    # Adam's second moment after the spike is that of norm c, not 1e24 times larger.
    _, state = clipped.update(jax.tree.map(lambda d: d * 1e12, direction), clipped.init(params), params)
    nu = state[1][0].nu["a"]
    np.testing.assert_allclose(nu, 0.001 * (np.array([3.0, 0.0, -4.0]) * clip / 5.0) ** 2, rtol=1e-6)


def test_learning_rate_decay_is_a_cosine_over_the_last_share_of_the_steps():
    """--train.lr_decay_share=s: the rate is constant for the first (1 - s) x num_steps updates, then
    lr * (1 + cos(pi * k / D)) / 2 over the last D = s x num_steps (k updates into them), zero at the end;
    Adam's updates scale with it (a first update is lr times the gradient's sign)."""
    lr, steps, share = 1e-3, 100, 0.4
    cfg = config.replace(CFG, train=dict(learning_rate=lr, num_steps=steps, lr_decay_share=share, max_grad_norm=0.0))
    decay = round(share * steps)
    for step in (0, 59, 60, 70, 80, 99, 100):
        k = max(0, step - (steps - decay))
        want = lr * 0.5 * (1.0 + np.cos(np.pi * min(k, decay) / decay))
        assert train.learning_rate_at(cfg, step) == pytest.approx(want, abs=1e-9), step  # float32: 1e-6 of lr
    assert train.learning_rate_at(config.replace(cfg, train=dict(lr_decay_share=0.0)), 99) == lr
    # the compiled step's config keeps the schedule (it reads num_steps once the rate decays)
    assert [train.learning_rate_at(train.step_config(cfg), k) for k in range(steps)] == [
        train.learning_rate_at(cfg, k) for k in range(steps)
    ]
    params = {"a": np.ones(3, np.float32)}
    grads = {"a": np.array([2.0, -3.0, 0.5], np.float32)}
    opt = train.optimizer(cfg)
    adam_state, schedule_state = opt.init(params)
    half_way = schedule_state._replace(count=np.int32(80))  # update 80, half-way down the cosine: lr / 2
    updates, _ = opt.update(grads, (adam_state, half_way), params)
    np.testing.assert_allclose(updates["a"], -0.5 * lr * np.sign(grads["a"]), rtol=1e-4)


def test_a_decaying_run_resumes_under_another_num_steps_only_before_its_decay(tmp_path):
    """A run of 10 steps decaying over the last 3 (from update 7) saved at step `saved`: resuming it with
    --train.num_steps=20 (decay from 14) follows the steps already trained only if both starts lie ahead."""
    decaying = config.replace(CFG, train=dict(num_steps=10, lr_decay_share=0.3))
    assert (
        train_state.decay_start(decaying),
        train_state.decay_start(config.replace(decaying, train=dict(num_steps=20))),
    ) == (7, 14)
    for saved, resumable in ((7, True), (8, False)):
        workdir = tmp_path / str(saved)
        workdir.mkdir()
        (workdir / "config.json").write_text(decaying.to_json())
        with checkpoint.manager(str(workdir)) as manager:
            manager.save(saved, args=ocp.args.StandardSave(train.init_state(decaying)))
        longer = config.replace(decaying, train=dict(num_steps=20))
        if resumable:
            assert checkpoint.check_resumable(longer, str(workdir)) == saved
        else:
            with pytest.raises(ValueError, match=r"--train\.num_steps=20: .* reached step 8, .* decays from step 7"):
                checkpoint.check_resumable(longer, str(workdir))
        assert checkpoint.check_resumable(decaying, str(workdir)) == saved  # its own count resumes
        constant = config.replace(longer, train=dict(lr_decay_share=0.0))
        (workdir / "config.json").write_text(config.replace(decaying, train=dict(lr_decay_share=0.0)).to_json())
        assert checkpoint.check_resumable(constant, str(workdir)) == saved  # a constant rate extends freely


@pytest.mark.slow
def test_stops_after_max_nonfinite_in_a_row_keeping_the_last_good_checkpoint(tmp_path):
    # Steps 0, 1 update; 2, 3, 4 are non-finite (the 3rd in a row halts updates), found at the log of step 6.
    with pytest.raises(
        train.NonFiniteLossError,
        match=r"stopping at step 6: 3 non-finite .*"
        r"--train\.max_nonfinite_in_a_row=3.*step 4",
    ):
        train.train(CFG, str(tmp_path), batches=synthetic_batches(nan_steps=range(2, 100)))
    assert checkpoint_steps(tmp_path) == [2, 4]
    assert_trees_equal(saved_params(tmp_path, 4), saved_params(tmp_path, 2))  # the skips changed nothing
    records = read_jsonl(tmp_path / "metrics.jsonl")
    assert [(r["nonfinite_in_a_row"], r["nonfinite_total"]) for r in records] == [(0, 0), (2, 2), (3, 4)]
    assert np.isfinite(records[0]["total"]) and not np.isfinite(records[1]["total"])


# ----------------------------------------------------------------------------- logs and resuming


@pytest.mark.slow
def test_logs_metrics_progress_and_resumes(tmp_path, capsys):
    train.train(CFG, str(tmp_path), batches=synthetic_batches(stop=4))  # data ends: checkpoint at exit
    records = read_jsonl(tmp_path / "metrics.jsonl")
    assert [r["step"] for r in records] == [2, 4]
    assert set(records[0]) >= {
        "recon_camera",
        "recon_lidar",
        "recon_roadmap",
        "kl",
        "det_cls",
        "det_reg",
        *POSE_TERMS,
        "total",
        "grad_norm",
        "steps_per_s",
        "nonfinite_total",
    }
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


@pytest.mark.slow
def test_launcher_with_a_coordinator_counts_both_processes_devices_before_any_compile(tmp_path):
    """Both processes of a 2-process run in parallel. jax.distributed.initialize makes their 2 devices one mesh,
    so the batch-size error counts both; JAX_LOG_COMPILES=1 logs any compilation to stderr, so a one-line
    stderr proves nothing was compiled. (The other launcher errors are rows of test_bad_input.py.)"""
    port = free_port()
    coordinator = [f"--coordinator_address=localhost:{port}", "--num_processes=2", "--data.batch_size=3"]
    procs = [
        subprocess.Popen(
            LAUNCHER + TINY_FLAGS + [f"--workdir={tmp_path / str(i)}", f"--process_id={i}"] + coordinator,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=dict(os.environ, JAX_LOG_COMPILES="1"),
        )
        for i in range(2)
    ]
    for i, proc in enumerate(procs):
        out, err = proc.communicate(timeout=300)
        assert (
            proc.returncode == 1
            and err.count("\n") == 1
            and err.startswith("error: ")
            and ("--data.batch_size=3 must be a multiple of the number of devices (2)" in err)
        ), (i, out + err)
        assert not (tmp_path / str(i)).exists() or not os.listdir(tmp_path / str(i)), i  # nothing written


# ----------------------------------------------------------------------------- data parallel


@pytest.mark.slow
def test_four_devices_equal_one_device(subprocess_runs):
    """Loss and gradients with the batch sharded over 4 simulated CPU devices (a subprocess) equal 1 device."""
    metrics4, grads4 = subprocess_runs["four_devices"].result()
    params = model.init_params(jax.random.PRNGKey(0), TINY)
    (_, metrics1), grads1 = jax.device_get(
        loss_and_grads(params, synthetic_batch(0, TINY, batch_size=4), jax.random.PRNGKey(7), TINY)
    )
    assert set(metrics4) == set(metrics1)
    for k in metrics1:
        np.testing.assert_allclose(metrics4[k], metrics1[k], rtol=1e-5, err_msg=k)

    # float32 sums over pixels and rows in another order (the loss is O(1e4), so a bias gradient sums
    # large terms that cancel): each gradient's error relative to its norm; a wrong row or shard gives O(1)
    def check(path, g4, g1):
        error = np.linalg.norm(g4 - g1) / np.linalg.norm(g1)
        assert error < 1e-3, (jax.tree_util.keystr(path), error)

    jax.tree_util.tree_map_with_path(check, grads4, grads1)


# ----------------------------------------------------------------------------- real world batches

KILL_STEPS = 20  # N of the stop-and-resume tests
WORLD_STEPS = 250
HELD_OUT_STEP = 10**6  # the run's data stream from this step on: batches the run never trains on


@pytest.fixture(scope="module")
def world_run(tmp_path_factory):
    """The tiny model on the world's batches to KILL_STEPS (the uninterrupted reference of the stop tests),
    then resumed on to WORLD_STEPS. Returns (params at KILL_STEPS, params at WORLD_STEPS, metrics records,
    8 held-out batches)."""
    workdir = str(tmp_path_factory.mktemp("world"))
    batches = train.world_batches(tiny())  # the town is built once
    at_kill_steps = jax.device_get(train.train(tiny(num_steps=KILL_STEPS, log_every=10), workdir, batches).params)
    at_end = train.train(tiny(num_steps=WORLD_STEPS, log_every=10, checkpoint_every=WORLD_STEPS), workdir, batches)
    held_out = [batch for _, (_, batch) in zip(range(8), batches(HELD_OUT_STEP))]
    return at_kill_steps, jax.device_get(at_end.params), read_jsonl(os.path.join(workdir, "metrics.jsonl")), held_out


@pytest.mark.slow
def test_tiny_run_on_world_batches_lowers_every_loss_term(world_run):
    """Every term, with posterior means on the same 8 held-out batches, is lower at the end than at step
    KILL_STEPS. Not from step 0: the KL starts near zero (q and p alike at initialisation) and peaks within
    the first steps, once the posterior encodes the frames; comparing fixed batches removes the noise of
    how many vehicles each training batch holds (det_reg is non-zero only at vehicles)."""
    at_kill_steps, at_end, records, held_out = world_run
    assert [r["step"] for r in records] == list(range(10, WORLD_STEPS + 1, 10))
    # TINY has the run's model section, so this reuses the loss tests' compilation.
    mean_terms = lambda params: jax.tree.map(
        lambda *x: np.mean(x),
        *[jax.device_get(loss.loss_fn(params, {k: b[k] for k in loss.BATCH_KEYS}, None, TINY)[1]) for b in held_out],
    )
    start, end = mean_terms(at_kill_steps), mean_terms(at_end)
    assert len(start) == 11  # 10 terms (4 of them the pose belief's) and the total
    # Not the per-cell offsets: each of the 2,304 cells' offsets learns only where an ego has been, and this
    # run sees ~2,000 frames, so held-out batches fall on cells it has barely visited.
    for k in set(start) - {"pose_offset"}:
        assert end[k] < start[k], f"{k}: {start[k]:.4g} at step {KILL_STEPS}, {end[k]:.4g} at step {WORLD_STEPS}"
    assert np.isfinite(end["pose_offset"])


def launch(workdir, cache, env):
    """The launcher on the world run's config, in environment ``env``; compilations are shared through a
    persistent cache."""
    return subprocess.Popen(
        LAUNCHER
        + TINY_FLAGS
        + [
            f"--workdir={workdir}",
            f"--train.num_steps={KILL_STEPS}",
            "--train.checkpoint_every=2",
            "--train.log_every=10",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(env, JAX_COMPILATION_CACHE_DIR=str(cache)),
    )


def wait_for_checkpoint(proc, workdir, after):
    """Waits until ``workdir`` has a finished checkpoint later than ``after``, the run still going."""
    deadline = time.time() + 300
    while time.time() < deadline:
        if checkpoint_steps(workdir) and checkpoint_steps(workdir)[-1] > after:
            return
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.02)
    raise TimeoutError


def stop_and_resume(tmp_path, signum, env, motion_model_from=None):
    """The launcher to KILL_STEPS in a run of its own, sent ``signum`` after its first checkpoint, then
    resumed to the end. Returns (its exit status, its last checkpoint, its stderr, the resumed run's
    stdout, the parameters saved at KILL_STEPS). ``motion_model_from``: a run whose fitted motion model
    this one starts with (the fit is the same; the launcher then skips it)."""
    workdir, cache = str(tmp_path / signal.Signals(signum).name), tmp_path / "cache"
    if motion_model_from is not None:
        os.makedirs(workdir)
        shutil.copy(os.path.join(motion_model_from, "motion_model.json"), workdir)
    proc = launch(workdir, cache, env)
    wait_for_checkpoint(proc, workdir, after=0)
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=300)
    status, stopped_at = proc.returncode, checkpoint_steps(workdir)[-1]
    proc = launch(workdir, cache, env)
    out, resumed_err = proc.communicate(timeout=600)
    assert proc.returncode == 0, out + resumed_err
    return status, stopped_at, err, out, saved_params(workdir, KILL_STEPS)


def stops_and_resumes(tmp_path, env):
    """SIGKILL (nothing saved at the kill), then SIGTERM (the launcher saves the step it was on), one after
    the other so the second reuses the first's compilation cache and motion model."""
    killed = stop_and_resume(tmp_path, signal.SIGKILL, env)
    stopped = stop_and_resume(tmp_path, signal.SIGTERM, env, motion_model_from=tmp_path / signal.SIGKILL.name)
    return {signal.SIGKILL: killed, signal.SIGTERM: stopped}


@pytest.mark.slow
def test_sigkill_then_resume_equals_an_uninterrupted_run(subprocess_runs, world_run):
    status, killed_at, _, out, params = subprocess_runs["stops"].result()[signal.SIGKILL]
    assert status == -signal.SIGKILL
    assert 0 < killed_at < KILL_STEPS
    assert f"resumed from step {killed_at}" in out, out
    assert_trees_equal(params, world_run[0])


@pytest.mark.slow
def test_sigterm_saves_the_step_it_was_on_and_resume_equals_an_uninterrupted_run(subprocess_runs, world_run):
    """The launcher finishes the step it is on, checkpoints it (on any step, not only a multiple of
    checkpoint_every), says so in one line and exits with 128 + SIGTERM; a rerun continues from there."""
    status, stopped_at, err, out, params = subprocess_runs["stops"].result()[signal.SIGTERM]
    assert status == 128 + signal.SIGTERM, err
    assert 0 < stopped_at < KILL_STEPS
    assert f"interrupted by SIGTERM at step {stopped_at}; checkpoint saved" in err, err
    assert f"resumed from step {stopped_at}" in out, out
    assert_trees_equal(params, world_run[0])


@pytest.mark.slow
@pytest.mark.parametrize("model_fields", [dict(detection_input="latent_and_features"), dict(latent="bev")])
def test_a_run_with_the_place_stream_resumes_bit_identically(tmp_path, model_fields):
    """The presets' stream (drives of several batches, place frames beside them), with the PIXOR decoder reading
    the frame's features or with the bird-eye latent: a run stopped at step 2 and resumed equals the
    uninterrupted one."""
    cfg = config.replace(
        tiny(num_steps=4, checkpoint_every=2, log_every=2),
        data=dict(batches_per_drive=2, place_frames=2),
        model=model_fields,
    )
    batches = train.world_batches(cfg)
    whole = train.train(cfg, str(tmp_path / "whole"), batches)
    train.train(config.replace(cfg, train=dict(num_steps=2)), str(tmp_path / "stopped"), batches)
    resumed = train.train(cfg, str(tmp_path / "stopped"), batches)
    assert_trees_equal(jax.device_get(resumed.params), jax.device_get(whole.params))
    last = lambda run: read_jsonl(tmp_path / run / "metrics.jsonl")[-1]
    assert (last("stopped")["step"], last("stopped")["pose_place"]) == (
        last("whole")["step"],
        last("whole")["pose_place"],
    )


@pytest.mark.slow
@pytest.mark.parametrize("latent", config.LATENTS)
def test_carried_state_chains_segments_and_resumes_bit_identically(tmp_path, latent):
    """With --data.carry_state the step starts each drive's first segment afresh (its loss is the plain
    loss's) and continues later ones from the carry its slot left (the bird-eye grid too); a run stopped and
    resumed equals the uninterrupted one, carry included."""
    cfg = config.replace(
        CFG, data=dict(batches_per_drive=2, carry_state=True), train=dict(num_steps=6), model=dict(latent=latent)
    )
    whole = train.train(cfg, str(tmp_path / "whole"), batches=synthetic_batches())
    train.train(config.replace(cfg, train=dict(num_steps=3)), str(tmp_path / "stopped"), batches=synthetic_batches())
    resumed = train.train(cfg, str(tmp_path / "stopped"), batches=synthetic_batches())
    assert_trees_equal(jax.device_get(resumed), jax.device_get(whole))

    # the very step the runs above compiled (its inputs placed as train.train places them): no compile of its own
    mesh = train.make_mesh()
    state = jax.device_put(train.init_state(cfg), jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
    step_fn = lambda s, b, k: train.make_train_step(cfg, mesh)(s, train.shard_batch(b, mesh, cfg), k)
    batches = [{k: b[k] for k in loss.BATCH_KEYS} for _, b in itertools.islice(synthetic_batches()(0), 3)]
    key = jax.random.PRNGKey(5)
    fresh = jax.jit(lambda p, b: loss.loss_fn(p, b, key, cfg)[1]["total"])
    # steps 0 and 1: segment 0 of the drives in slots 0 and 1 (fresh); step 2: slot 0's segment 1
    for b in batches[:2]:
        expected = fresh(state.params, b)
        state, metrics = step_fn(state, b, key)
        np.testing.assert_allclose(metrics["total"], expected, rtol=1e-6)
    start = (
        model.FilterState(**{k: v[0] for k, v in state.carry.items() if k != "action"}, first=np.zeros(2, bool)),
        state.carry["action"][0],
    )
    np.testing.assert_array_equal(state.carry["action"][0], batches[0]["action"][:, -1])
    expected = loss.sequence_loss(state.params, batches[2], key, cfg, start)[0]
    assert not np.allclose(expected, fresh(state.params, batches[2]), rtol=1e-4)
    np.testing.assert_allclose(step_fn(state, batches[2], key)[1]["total"], expected, rtol=1e-6)


@pytest.mark.slow
def test_resume_from_a_damaged_latest_checkpoint_falls_back_to_the_newest_intact_one(tmp_path, capsys):
    """The latest checkpoint truncated: the run says so in one line, keeps it as <step>.damaged, resumes from
    the one before, and ends where an uninterrupted run ends; the older checkpoints are untouched."""
    train.train(CFG, str(tmp_path / "whole"), batches=synthetic_batches())
    run = tmp_path / "damaged"
    train.train(CFG, str(run), batches=synthetic_batches(stop=6))
    assert checkpoint_steps(run) == [2, 4, 6]
    step6 = run / "checkpoints" / "6"
    largest = max((os.path.join(d, f) for d, _, names in os.walk(step6) for f in names), key=os.path.getsize)
    with open(largest, "r+b") as f:
        f.truncate(os.path.getsize(largest) // 2)
    capsys.readouterr()
    state = train.train(CFG, str(run), batches=synthetic_batches())
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and f"checkpoint {step6}: cannot be restored" in err and ".damaged" in err, err
    assert "resumed from step 4" in out
    assert (run / "checkpoints" / "6.damaged").is_dir()
    assert [r["step"] for r in read_jsonl(run / "metrics.jsonl")] == [2, 4, 6, 8]
    assert_trees_equal(saved_params(run, 8), saved_params(tmp_path / "whole", 8))
    assert int(state.step) == 8


@pytest.mark.slow
def test_the_remembered_weight_reads_who_saw_each_box_from_the_worlds_batches(world_run):
    """--train.remembered_weight on the world's batches, which carry the loss's memory keys: the weighted
    detection terms exceed the plain ones exactly where a batch holds a remembered vehicle's positive pixels
    (the tiny sequences hold none, so one held-out batch's nearest vehicle is hidden from both sensors by
    hand in its last frame), and every other term is unchanged."""
    _, params, _, held_out = world_run
    weighted_cfg = config.replace(TINY, train=dict(remembered_weight=4.0))
    hidden = dict(held_out[0])
    near = np.argmin(
        np.where(hidden["boxes_valid"][0, -1], np.linalg.norm(hidden["boxes"][0, -1, :, :2], axis=-1), np.inf)
    )
    for k, value in (("boxes_lidar_visible", False), ("boxes_camera_visible", False), ("boxes_frames_since_seen", 1)):
        hidden[k] = np.array(hidden[k])
        hidden[k][0, -1, near] = value
    holds = []
    for b in [hidden] + held_out:
        plain = jax.device_get(loss.loss_fn(params, {k: b[k] for k in loss.batch_keys(TINY) if k in b}, None, TINY)[1])
        weighted = jax.device_get(
            loss.loss_fn(params, {k: b[k] for k in loss.batch_keys(weighted_cfg) if k in b}, None, weighted_cfg)[1]
        )
        holds.append(bool(np.any(np.asarray(loss.group_pixels(b, "remembered")) & (np.asarray(b["det_cls"]) > 0.5))))
        assert (weighted["det_cls"] > plain["det_cls"]) == holds[-1]
        for k in set(plain) - {"det_cls", "det_reg", "total"}:
            assert weighted[k] == plain[k], k
    assert holds[0]
