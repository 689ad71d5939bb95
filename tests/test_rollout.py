"""The one driving loop: its three forms drive the same world the same way."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from e2e_percep_jax import config, rollout, world

CFG = config.get_config("tiny")


@pytest.fixture(scope="module")
def start(town):
    return world.reset(jax.random.PRNGKey(3), town, CFG.world)


def test_advance_is_that_many_single_steps(town, start):
    stepped, step = start, jax.jit(world.step)
    for _ in range(7):
        stepped = step(stepped, town)
    advanced = jax.jit(rollout.advance, static_argnums=2)(start, town, 7)
    # The same operations, compiled as one loop or as seven calls: equal up to float32 rounding.
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-4), advanced, stepped)


@pytest.mark.slow
def test_drive_chains_and_returns_the_states_it_saw(town, start):
    drive = jax.jit(rollout.drive, static_argnums=(2, 3, 4))
    last, frames, states = drive(start, town, 6, 32, True)
    first_half_last, first_half = drive(start, town, 3, 32)
    _, second_half = drive(first_half_last, town, 3, 32)
    for name in frames:  # two drives of 3 frames, chained, are one drive of 6
        np.testing.assert_array_equal(frames[name], np.concatenate([first_half[name], second_half[name]]), err_msg=name)
    jax.tree.map(np.testing.assert_array_equal, jax.tree.map(lambda x: x[0], states), start)
    jax.tree.map(np.testing.assert_array_equal, last, jax.jit(rollout.advance, static_argnums=2)(start, town, 6))
    # action t is the ego action applied from t to t+1: the ego_action of state t+1
    np.testing.assert_array_equal(frames.action[:-1], states.ego_action[1:])
    np.testing.assert_array_equal(frames.action[-1], last.ego_action)


def test_frames_are_a_read_only_mapping_of_the_contract(town, start):
    _, frames = jax.jit(rollout.drive, static_argnums=(2, 3))(start, town, 2, 32)
    assert list(frames) == ["camera", "lidar", "roadmap", "det_cls", "det_reg", "pose", "action", "boxes",
                            "boxes_valid", "boxes_occluded"]
    assert frames["camera"] is frames.camera and frames.camera.shape == (2, 32, 32, 3)
    assert dict(frames).keys() == set(frames) and len(frames) == 10
    with pytest.raises(KeyError):
        frames["replace"]  # a dataclass method, not a field


@pytest.mark.slow
def test_drive_perceiving_sees_the_frames_drive_records(town, start):
    """A perceiver that copies what it is shown: after ``warm`` unobserved steps, frame t is ``drive``'s
    frame warm + t, its previous action ``drive``'s action warm + t - 1; warm-up frames give zeros."""
    warm, num = 2, 5
    worlds = jax.tree.map(lambda x: jnp.stack([x, x]), start)  # two identical worlds: the W axis

    def perceive(count, frame, prev_action, key):
        return count + 1, {"pose": frame["pose"], "prev_action": prev_action, "key": key}

    keys = jax.random.split(jax.random.PRNGKey(0), num)
    run = jax.jit(lambda w: rollout.drive_perceiving(w, jnp.int32(0), town, 32, keys, jnp.arange(num) < warm, perceive))
    last, count, out = run(worlds)
    _, frames = rollout.drive(start, town, num, 32)
    assert int(count) == num - warm
    np.testing.assert_array_equal(out["pose"][:warm], 0)
    np.testing.assert_array_equal(out["key"][warm:], keys[warm:])
    for t in range(warm, num):
        for w in range(2):
            np.testing.assert_array_equal(out["pose"][t, w], frames.pose[t])
            np.testing.assert_array_equal(out["prev_action"][t, w], frames.action[t - 1])
    stepped = jax.jit(rollout.advance, static_argnums=2)(start, town, num)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a[0], b, rtol=1e-5, atol=1e-4), last, stepped)
