"""The one driving loop: ``advance`` and ``drive`` step the world as single steps do, and ``drive`` pairs each
frame with the action that follows it. (``drive_perceiving`` is pinned by the evaluation's tests: the
oracle sees every frame's truth through it, and the known-start odometry follows its previous actions.)"""

import jax
import numpy as np
import pytest

from e2e_percep_jax import config
from e2e_percep_jax.sim import rollout, world

CFG = config.get_config("tiny")
NUM_FRAMES, IMAGE_SIZE = 3, 32
advance = jax.jit(rollout.advance, static_argnums=2)


@pytest.fixture(scope="module")
def start(town):
    return jax.jit(world.reset, static_argnums=2)(jax.random.PRNGKey(3), town, CFG.world)  # (one program, not op by op)


@pytest.fixture(scope="module")
def drive(town):
    """``rollout.drive`` of NUM_FRAMES frames with the states it saw, compiled once for the module."""
    run = jax.jit(lambda state: rollout.drive(state, town, NUM_FRAMES, IMAGE_SIZE, with_states=True))
    return lambda state: jax.tree.map(np.asarray, run(state))


def test_advance_is_that_many_single_steps(town, start):
    stepped, step = start, jax.jit(world.step)
    for _ in range(NUM_FRAMES):
        stepped = step(stepped, town)
    # The same operations, compiled as one loop or as single calls: equal up to float32 rounding. (As many
    # steps as the drive below takes, whose end is compared with the same compiled loop.)
    jax.tree.map(
        lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-4), advance(start, town, NUM_FRAMES), stepped
    )


def test_drive_returns_the_next_frames_state_and_the_states_it_saw(town, start, drive):
    last, frames, states = drive(start)
    jax.tree.map(np.testing.assert_array_equal, jax.tree.map(lambda x: x[0], states), start)
    jax.tree.map(np.testing.assert_array_equal, last, advance(start, town, NUM_FRAMES))  # drives chain
    # action t is the ego action applied from t to t+1: the ego_action of state t+1
    np.testing.assert_array_equal(frames.action[:-1], states.ego_action[1:])
    np.testing.assert_array_equal(frames.action[-1], last.ego_action)


def test_frames_are_a_read_only_mapping_of_the_contract(start, drive):
    _, frames, _ = drive(start)
    assert list(frames) == [
        "camera",
        "lidar",
        "lidar_scan",
        "roadmap",
        "det_cls",
        "det_reg",
        "pose",
        "action",
        "boxes",
        "boxes_valid",
        "boxes_lidar_visible",
        "boxes_camera_visible",
        "boxes_frames_since_seen",
    ]
    assert frames["camera"] is frames.camera and frames.camera.shape == (NUM_FRAMES, IMAGE_SIZE, IMAGE_SIZE, 3)
    assert dict(frames).keys() == set(frames) and len(frames) == 13
    with pytest.raises(KeyError):
        frames["replace"]  # a dataclass method, not a field
