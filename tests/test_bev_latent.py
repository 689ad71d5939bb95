"""The bird-eye latent grid (``--model.latent=bev``): its warp by the ego's motion against closed forms, the
ego's motion between two poses, its per-cell KL and motion terms against NumPy, streaming against the
training scan, and the README's inference example on a trained run with the grid."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import TINY, np_kl, run_readme_example, synthetic_batch

from e2e_percep_jax import bev_latent, loss, model
from e2e_percep_jax import config as config_lib
from e2e_percep_jax import train as train_lib
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import sensors

CFG = config_lib.replace(TINY, model=dict(latent="bev"))
G8_CELL_M = 32.0 / 8  # the BEV view is 32 m square: 4 m cells at G = 8, the ego on the corner of row 5, column 4


def _grid(g=8, channels=3, seed=0):
    return np.random.default_rng(seed).normal(size=(1, g, g, channels)).astype(np.float32)


@pytest.mark.parametrize(
    "motion_cells, shift_rows, shift_cols",
    [((2, 0), 2, 0), ((0, 1), 0, 1), ((-1, -3), -1, -3), ((0, 0), 0, 0)],
)
def test_a_translation_by_whole_cells_shifts_the_grid(motion_cells, shift_rows, shift_cols):
    """The ego moves ahead by k cells: what was k rows further ahead is now in its row (rows grow backwards);
    moving left (+y) by k cells shifts the content k columns to the right. New cells hold zeros, inside 0."""
    grid = _grid()
    motion = jnp.array([[motion_cells[0] * G8_CELL_M, motion_cells[1] * G8_CELL_M, 0.0]])
    warped, inside = map(np.asarray, bev_latent.warp(jnp.asarray(grid), motion))
    want, seen = np.zeros_like(grid), np.zeros(grid.shape[:3] + (1,), np.float32)
    rows, cols = slice(max(shift_rows, 0), 8 + min(shift_rows, 0)), slice(max(shift_cols, 0), 8 + min(shift_cols, 0))
    src_rows = slice(max(-shift_rows, 0), 8 + min(-shift_rows, 0))
    src_cols = slice(max(-shift_cols, 0), 8 + min(-shift_cols, 0))
    want[:, rows, cols], seen[:, rows, cols] = grid[:, src_rows, src_cols], 1.0
    np.testing.assert_allclose(warped, want, atol=1e-6)
    np.testing.assert_array_equal(inside, seen)


def test_a_quarter_turn_about_the_ego_moves_cells_by_the_closed_form():
    """A left turn of 90 degrees on the spot (the ego on a cell corner at G = 8): cell (i, j) of the new frame,
    centred at (x, y) = (20 - 4 (i + 1/2), 16 - 4 (j + 1/2)) m, lay at (-y, x) in the old one, which is old
    cell (8 - j, i - 1). Row 0 (18 m ahead, beyond the old view's 16 m to the left) and column 0 (14 m left,
    beyond the 12 m behind) are new."""
    grid = _grid(seed=1)
    warped, inside = map(np.asarray, bev_latent.warp(jnp.asarray(grid), jnp.array([[0.0, 0.0, np.pi / 2]])))
    want, seen = np.zeros_like(grid), np.zeros(grid.shape[:3] + (1,), np.float32)
    for i in range(8):
        for j in range(8):
            if 0 <= 8 - j < 8 and 0 <= i - 1 < 8:
                want[0, i, j], seen[0, i, j] = grid[0, 8 - j, i - 1], 1.0
    np.testing.assert_allclose(warped, want, atol=1e-5)
    np.testing.assert_allclose(inside, seen, atol=1e-5)
    assert seen.sum() == 49


def test_a_motion_and_its_inverse_give_back_the_cells_both_frames_see():
    """Warped by a motion and then by its inverse, a field linear in the cell indices (which bilinear sampling
    reproduces exactly) comes back wherever both warps sampled whole cells."""
    dx, dy, dyaw = 1.3, -0.4, 0.21
    inverse = [-(np.cos(dyaw) * dx + np.sin(dyaw) * dy), -(-np.sin(dyaw) * dx + np.cos(dyaw) * dy), -dyaw]
    field = np.fromfunction(lambda b, i, j, c: 0.3 * i - 0.2 * j + c, (1, 16, 16, 2)).astype(np.float32)
    there, inside_there = bev_latent.warp(jnp.asarray(field), jnp.array([[dx, dy, dyaw]]))
    back, _ = bev_latent.warp(there, jnp.array([inverse], jnp.float32))
    # a cell comes back exactly where every cell it samples was itself sampled whole
    whole_there = (np.asarray(inside_there) > 1 - 1e-5).astype(np.float32)
    kept = np.asarray(bev_latent.warp(jnp.asarray(whole_there), jnp.array([inverse], jnp.float32))[0])[0, ..., 0]
    kept = kept > 1 - 1e-5
    assert kept.sum() > 150
    np.testing.assert_allclose(np.asarray(back)[0][kept], field[0][kept], atol=1e-4)


def test_the_scene_flow_carries_each_cell_by_its_own_flow():
    """``transport`` against the closed form: a flow of one whole cell ahead carries every cell's content one row
    up (rows grow backwards; the last row has nothing behind it, zeros); a cell's own flow moves only what
    arrives there (one cell takes its left neighbour's content, the rest keep theirs); no flow is the identity;
    and the flow gets a gradient (what the prior learns it from) equal to the bilinear sample's slope."""
    grid = _grid()
    ahead = np.zeros((1, 8, 8, 2), np.float32)
    ahead[..., 0] = G8_CELL_M
    want = np.zeros_like(grid)
    want[:, :-1] = grid[:, 1:]
    transport = jax.jit(bev_latent.transport)
    np.testing.assert_allclose(np.asarray(transport(jnp.asarray(grid), jnp.asarray(ahead))), want, atol=1e-6)
    one_cell = np.zeros((1, 8, 8, 2), np.float32)
    one_cell[0, 3, 5, 1] = -G8_CELL_M  # moved right (-y) by a cell: it came from column 4
    want = grid.copy()
    want[0, 3, 5] = grid[0, 3, 4]
    np.testing.assert_allclose(np.asarray(transport(jnp.asarray(grid), jnp.asarray(one_cell))), want, atol=1e-6)
    np.testing.assert_allclose(np.asarray(transport(jnp.asarray(grid), jnp.zeros((1, 8, 8, 2)))), grid, atol=1e-6)
    # a quarter cell ahead at cell (3, 5), channel 0: d/d(flow x) of the sample = (grid[4] - grid[3]) / cell_m
    pick = lambda f: transport(jnp.asarray(grid), f)[0, 3, 5, 0]
    flow = jnp.zeros((1, 8, 8, 2)).at[0, 3, 5, 0].set(0.25 * G8_CELL_M)
    slope = jax.grad(pick)(flow)[0, 3, 5, 0]
    np.testing.assert_allclose(slope, (grid[0, 4, 5, 0] - grid[0, 3, 5, 0]) / G8_CELL_M, rtol=1e-5)


def test_on_a_lattice_translations_move_the_grid_by_whole_cells_and_add_up_to_one_warp():
    """Twelve fractions of a cell forward and sideways: on the lattice every value the grid holds is one it
    held before (whole cells, no blur; new cells zero), the offset stays within half a cell, and the grid read
    on the ego's cells equals one bilinear warp of the first grid by the summed motion. The bilinear warp,
    applied frame by frame, blurs: its peak falls."""
    rng = np.random.default_rng(2)
    grid = _grid(g=16, channels=2, seed=2)
    steps = np.concatenate([rng.uniform(0.2, 1.3, (12, 1)), rng.uniform(-0.4, 0.4, (12, 1)), np.zeros((12, 1))], 1)
    lattice, offset, frame_by_frame = jnp.asarray(grid), jnp.zeros((1, 2)), jnp.asarray(grid)
    on_lattice, warp = jax.jit(bev_latent.warp_on_lattice), jax.jit(bev_latent.warp)  # one compile each
    for motion in steps.astype(np.float32):
        lattice, _, offset = on_lattice(lattice, offset, jnp.asarray(motion[None]))
        frame_by_frame, _ = warp(frame_by_frame, jnp.asarray(motion[None]))
        assert np.all(np.abs(np.asarray(offset)) <= 2.0 / 2 + 1e-5)  # 2 m cells at G = 16
    values = np.asarray(lattice).ravel()
    nearest = np.abs(values[:, None] - np.append(grid.ravel(), 0.0)[None]).min(1)
    np.testing.assert_array_less(nearest, 1e-4)
    once, inside = bev_latent.warp(jnp.asarray(grid), jnp.asarray(steps.sum(0, keepdims=True), jnp.float32))
    # away from the view's edges, which the lattice lost and found again as the sideways steps went and came
    interior = np.zeros((16, 16), bool)
    interior[1:-1, 1:-1] = True
    interior &= np.asarray(inside)[0, ..., 0] > 1 - 1e-5
    assert interior.sum() > 100
    np.testing.assert_allclose(
        np.asarray(bev_latent.shift(lattice, -offset))[0][interior], np.asarray(once)[0][interior], atol=1e-4
    )
    assert np.abs(np.asarray(frame_by_frame)).max() < 0.8 * np.abs(np.asarray(lattice)).max()


def test_on_a_lattice_a_quarter_turn_is_the_bilinear_warp():
    """With the lattice on the ego's cells and no translation, the lattice's warp is the bilinear one (the
    quarter turn's closed form above) and its offset stays zero."""
    grid, turn = jnp.asarray(_grid(seed=1)), jnp.array([[0.0, 0.0, np.pi / 2]])
    warped, inside, offset = bev_latent.warp_on_lattice(grid, jnp.zeros((1, 2)), turn)
    want, want_inside = bev_latent.warp(grid, turn)
    np.testing.assert_allclose(warped, want, atol=1e-6)
    np.testing.assert_allclose(inside, want_inside, atol=1e-6)
    np.testing.assert_allclose(offset, 0.0, atol=1e-6)


def _vehicle_flow_by_hand(before, after, valid, motion, offset):
    """``bev_latent.vehicle_flow`` for one frame pair of boxes at yaw 0 in the later frame, cell by cell: a
    cell's centre inside a box grown by half a 4 m cell each way takes the mean of those boxes' moves, and is
    covered."""
    dx, dy, dyaw = motion
    c, s = np.cos(dyaw), np.sin(dyaw)
    rel = before[:, :2] - [dx, dy]
    earlier = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]], -1)  # rotated by -dyaw
    want, covered = np.zeros((8, 8, 2)), np.zeros((8, 8), bool)
    for row in range(8):
        for col in range(8):
            x, y = 20.0 - G8_CELL_M * (row + 0.5) + offset[0], 16.0 - G8_CELL_M * (col + 0.5) + offset[1]
            moves = [
                after[n, :2] - earlier[n]
                for n in range(len(after))
                if valid[n]
                and abs(x - after[n, 0]) <= 0.5 * (after[n, 3] + G8_CELL_M)
                and abs(y - after[n, 1]) <= 0.5 * (after[n, 4] + G8_CELL_M)
            ]
            if moves:
                want[row, col] = np.mean(moves, 0)
                covered[row, col] = True
    return want, covered


@pytest.mark.parametrize(
    "motion, offset",
    [((3.0, 0.0, 0.0), (0.0, 0.0)), ((0.0, 0.0, np.pi / 2), (0.0, 0.0)), ((1.5, 0.2, 0.1), (1.2, -0.7))],
)
def test_the_vehicle_flow_is_each_cars_move_on_the_cells_it_covers(motion, offset):
    """``bev_latent.vehicle_flow`` against a cell-by-cell count: a parked car's cells take no flow whatever the
    ego did (its earlier box, seen from the later frame, is where it is now), a car that drove 2 m ahead
    in the town gives its cells (2, 0), two cars side by side share a cell's mean, a car out of view marks
    nothing, and the lattice's offset moves the cells that are tested."""
    dx, dy, dyaw = motion
    c, s = np.cos(dyaw), np.sin(dyaw)
    to_earlier = lambda p: np.array([c * p[0] - s * p[1] + dx, s * p[0] + c * p[1] + dy])  # later -> earlier frame
    after = np.array(
        [[8.0, 6.0, 0, 4.5, 2.0], [-4.0, -6.0, 0, 4.5, 2.0], [2.0, -6.0, 0, 4.5, 2.0], [1.0, 1.0, 0, 4.5, 2.0]]
    )
    town_move = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 1.0], [1.0, 1.0]])  # in the later frame's axes
    before = np.array([np.r_[to_earlier(a[:2] - m), a[2:]] for a, m in zip(after, town_move)])
    valid = np.array([True, True, True, False])
    got, got_covered = bev_latent.vehicle_flow(
        jnp.asarray(before[None], jnp.float32),
        jnp.asarray(after[None], jnp.float32),
        jnp.asarray(valid[None]),
        jnp.asarray([motion], jnp.float32),
        8,
        jnp.asarray([offset], jnp.float32),
    )
    want, want_covered = _vehicle_flow_by_hand(before, after, valid, motion, offset)
    np.testing.assert_allclose(np.asarray(got[0]), want, atol=1e-5)
    np.testing.assert_array_equal(got_covered[0], want_covered)
    moving = np.abs(want).sum(-1) > 0
    assert 2 <= moving.sum() and np.allclose(want[moving & (want[..., 1] == 0)], [2.0, 0.0], atol=1e-5)
    assert want_covered[moving].all()


def test_relative_motion_is_the_later_pose_in_the_earlier_ego_frame():
    """Heading north (yaw pi/2) and moving 1 m north and 0.5 m west, turning 0.1 rad left: 1 m ahead, 0.5 m to
    the left, +0.1 rad; across the +-pi seam the heading change wraps."""
    before = jnp.array([10.0, 20.0, 0.0, 1.0, 5.0])
    after = jnp.array([9.5, 21.0, np.cos(np.pi / 2 + 0.1), np.sin(np.pi / 2 + 0.1), 5.0])
    np.testing.assert_allclose(bev_latent.relative_motion(before, after), [1.0, 0.5, 0.1], atol=1e-5)
    seam = lambda yaw: jnp.array([0.0, 0.0, np.cos(yaw), np.sin(yaw), 0.0])
    np.testing.assert_allclose(bev_latent.relative_motion(seam(3.1), seam(-3.1))[2], 2 * np.pi - 6.2, atol=1e-5)


@pytest.fixture(scope="module")
def params():
    return model.init_params(jax.random.PRNGKey(0), CFG)


@pytest.mark.slow
def test_a_zero_scene_flow_leaves_the_grid_as_the_egos_motion_does():
    """``--model.grid_motion=ego_and_flow`` adds the flow's network to the params; with its last layer at zero
    (no flow anywhere) the filter's outputs are the ego-only grid's with the same other params, and with the
    flow as drawn they are not."""
    cfg = config_lib.replace(CFG, model=dict(grid_motion="ego_and_flow"))
    with_flow = model.init_params(jax.random.PRNGKey(0), cfg)
    without = {"params": {k: v for k, v in with_flow["params"].items() if k != "grid_flow"}}
    assert jax.tree.structure(without) == jax.tree.structure(model.init_params(jax.random.PRNGKey(0), CFG))
    still = jax.tree.map(lambda x: x, with_flow)
    still["params"]["grid_flow"]["Conv_2"] = jax.tree.map(jnp.zeros_like, still["params"]["grid_flow"]["Conv_2"])
    batch = synthetic_batch(2, cfg)
    run = jax.jit(
        lambda p, c: model.filter_sequence(p, batch["camera"], batch["lidar"], batch["action"], None, c),
        static_argnums=1,
    )
    ego_only, zero_flow = run(without, CFG), run(still, cfg)
    np.testing.assert_array_equal(zero_flow.pop("flow"), 0.0)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, atol=1e-5), zero_flow, ego_only)
    moved = np.abs(np.asarray(run(with_flow, cfg)["p_grid_loc"] - ego_only["p_grid_loc"]))[:, 2:]
    assert moved.max() > 1e-2


def _with_boxes(batch, seed=3):
    """``batch`` with six random vehicles' boxes per frame (``boxes`` [B, T+1, 6, 5], ``boxes_valid``)."""
    b, t1 = batch["pose"].shape[:2]
    rng = np.random.default_rng(seed)
    boxes = np.concatenate([rng.uniform(-14, 14, (b, t1, 6, 2)), rng.uniform(-3, 3, (b, t1, 6, 1))], -1)
    boxes = np.concatenate([boxes, np.broadcast_to([4.5, 2.0], (b, t1, 6, 2))], -1).astype(np.float32)
    return dict(batch, boxes=boxes, boxes_valid=rng.uniform(size=(b, t1, 6)) < 0.7)


@pytest.mark.slow
def test_a_taught_flow_learns_from_the_vehicles_moves_alone():
    """With ``grid_motion="ego_and_taught_flow"`` no term but ``flow`` moves the flow's network (its gradient
    stopped where it carries the grid), while the grid still takes that term's gradient; with
    ``"ego_and_flow"`` the other terms move it too; with ``"ego_and_carried_flow"`` again ``flow`` alone."""

    def gradients(grid_motion):
        cfg = config_lib.replace(CFG, model=dict(grid_motion=grid_motion), train=dict(flow_weight=1.0))
        batch = _with_boxes(synthetic_batch(4, cfg))
        params = model.init_params(jax.random.PRNGKey(2), cfg)
        term = lambda name: (
            lambda p: (lambda m: m["total"] - m["flow"] if name == "rest" else m[name])(
                loss.loss_fn(p, batch, None, cfg)[1]
            )
        )
        return {name: jax.grad(term(name))(params)["params"] for name in ("rest", "flow")}

    norm = lambda tree: float(sum(jnp.sum(jnp.square(x)) for x in jax.tree.leaves(tree)))
    taught, learnt, carried = (gradients(m) for m in ("ego_and_taught_flow", "ego_and_flow", "ego_and_carried_flow"))
    assert norm(taught["rest"]["grid_flow"]) == 0.0 and norm(learnt["rest"]["grid_flow"]) > 0.0
    assert norm(taught["flow"]["grid_flow"]) > 0.0 and norm(taught["flow"]["q_grid"]) > 0.0
    assert norm(carried["rest"]["grid_flow"]) == 0.0 and norm(carried["flow"]["grid_flow"]) > 0.0


@pytest.mark.slow
def test_a_hidden_frame_carries_the_grid_and_its_flow_along_the_carried_flow():
    """``--model.grid_motion=ego_and_carried_flow`` with the ego standing (the motion head's last layer at zero)
    and no correction (the flow network's last layer at zero): on a frame the filter does not see, the state's
    flow of one cell a frame ahead carries itself and the grid one row ahead (row r takes row r + 1, the back
    row nothing), so the prior is the ego-only model's prior of the grid moved a row, away from the back rows
    that its convs reach; the flow and the lidar map kept are the state's, so moved and as they were."""
    cfg = config_lib.replace(CFG, model=dict(grid_motion="ego_and_carried_flow"), train=dict(flow_weight=1.0))
    params = model.init_params(jax.random.PRNGKey(4), cfg)
    still = jax.tree.map(lambda x: x, params)
    for net, layer in (("motion_head", "Dense_2"), ("grid_flow", "Conv_2")):
        still["params"][net][layer] = jax.tree.map(jnp.zeros_like, still["params"][net][layer])
    ego_params = {"params": {k: v for k, v in still["params"].items() if k != "grid_flow"}}
    b, g, c = 2, 16, cfg.model.grid_channels
    rng = np.random.default_rng(5)
    grid = rng.normal(size=(b, g, g, c)).astype(np.float32)
    lidar_before = rng.normal(size=(b, g, g, model.lidar_map_width(cfg.model, cfg.data.image_size))).astype(np.float32)
    state = model.init_filter_state(b, cfg).replace(
        first=jnp.zeros(b, bool),
        grid=jnp.asarray(grid),
        grid_flow=jnp.broadcast_to(jnp.array([16.0 * 2.0 / g, 0.0]), (b, g, g, 2)),  # 2 m ahead: a cell
        grid_lidar=jnp.asarray(lidar_before),
    )
    batch = synthetic_batch(6, cfg)
    camera, lidar, action = batch["camera"][:b, 1], batch["lidar"][:b, 1], batch["action"][:b, 0]

    def step(p, c, state):
        net = model.build_model(c)
        encoded = net.apply(p, camera, lidar, method=model.PerceptionModel.encode)
        hidden = jnp.zeros(b, bool)
        return net.apply(p, state, encoded, action, None, hidden, method=model.PerceptionModel.posterior_step)

    new_state, out = step(still, cfg, state)
    moved = np.zeros_like(grid)
    moved[:, :-1] = grid[:, 1:]
    ego_state = model.init_filter_state(b, CFG).replace(first=jnp.zeros(b, bool), grid=jnp.asarray(moved))
    _, ego_out = step(ego_params, CFG, ego_state)
    np.testing.assert_allclose(out["p_grid_loc"][:, : g - 4], ego_out["p_grid_loc"][:, : g - 4], atol=1e-5)
    assert np.abs(np.asarray(out["p_grid_loc"] - ego_out["p_grid_loc"]))[:, g - 1].max() > 1e-3  # the back row
    want_flow = np.zeros((b, g, g, 2), np.float32)
    want_flow[:, :-1, :, 0] = 2.0
    np.testing.assert_allclose(out["flow"], want_flow, atol=1e-5)
    np.testing.assert_allclose(new_state.grid_flow, want_flow, atol=1e-5)
    np.testing.assert_allclose(new_state.grid_lidar, lidar_before, atol=1e-5)


@pytest.mark.slow
def test_a_carried_flow_travels_in_the_drive_streams_carry():
    """With ``--data.carry_state`` a carried flow's state (its flow and lidar map) is part of each drive slot's
    carry: a step on slot 0 leaves there the scan's end state, the flow and map included (the same latent noise,
    so the same draws), and slot 1 untouched."""
    cfg = config_lib.replace(
        CFG,
        data=dict(batches_per_drive=2, carry_state=True),
        model=dict(grid_warp="lattice", grid_motion="ego_and_carried_flow"),
        train=dict(flow_weight=1.0),
    )
    state = train_lib.init_state(cfg)
    batch = _with_boxes(synthetic_batch(7, cfg))
    batch = {k: batch[k] for k in loss.batch_keys(cfg) if k in batch}
    key = jax.random.PRNGKey(8)
    stepped, _ = jax.jit(lambda s, b: train_lib.train_step(s, b, key, cfg))(state, batch)
    filtered = loss.sequence_loss(state.params, batch, key, cfg)[1][1]
    ended, _ = filtered
    for name in ("grid", "grid_offset", "grid_flow", "grid_lidar"):
        np.testing.assert_allclose(stepped.carry[name][0], getattr(ended, name), rtol=1e-4, atol=1e-5)
        np.testing.assert_array_equal(stepped.carry[name][1], 0.0)
    assert np.abs(np.asarray(stepped.carry["grid_flow"][0])).max() > 0.0


@pytest.mark.slow
def test_the_flow_term_is_the_flows_error_against_each_frame_pairs_vehicle_flow():
    """``--train.flow_weight``: the loss's ``flow`` is weight x perception weight x the squared error / 2 of the
    filter's flow (the cells a vehicle covers weighted by ``--train.flow_vehicle_weight``) against
    ``vehicle_flow`` of each pair of consecutive frames (their boxes, the poses' true motion, the lattice's
    offset of the later frame), summed over cells and frames 1..T, per sequence."""
    cfg = config_lib.replace(
        CFG,
        model=dict(grid_warp="lattice", grid_motion="ego_and_flow"),
        train=dict(flow_weight=2.0, flow_vehicle_weight=5.0),
    )
    batch = _with_boxes(synthetic_batch(3, cfg))
    b, t1 = batch["pose"].shape[:2]
    params = model.init_params(jax.random.PRNGKey(1), cfg)
    _, metrics = loss.loss_fn(params, batch, None, cfg)
    out = model.filter_sequence(params, batch["camera"], batch["lidar"], batch["action"], None, cfg)
    total, covered_cells = 0.0, 0
    for t in range(1, t1):
        motion = bev_latent.relative_motion(batch["pose"][:, t - 1], batch["pose"][:, t])
        target, covered = bev_latent.vehicle_flow(
            batch["boxes"][:, t - 1],
            batch["boxes"][:, t],
            batch["boxes_valid"][:, t],
            motion,
            16,
            out["grid_offset"][:, t],
        )
        weight = np.where(np.asarray(covered), 5.0, 1.0)[..., None]
        total += np.sum(0.5 * weight * np.square(np.asarray(out["flow"][:, t], np.float64) - np.asarray(target)))
        covered_cells += int(np.sum(covered))
    assert total > 0 and covered_cells > 0
    np.testing.assert_allclose(metrics["flow"], 2.0 * 32.0 * total / b, rtol=2e-4)


@pytest.mark.slow
def test_the_grid_kl_and_the_motion_term_match_numpy(params):
    """With posterior means the grid's KL term is the closed-form Gaussian KL summed over cells and channels,
    and the motion term the squared error in MOTION_UNIT units against the poses' relative motion, computed
    here with plain trigonometry; both per sequence. On first frames the grid's prior is N(0, I)."""
    batch = synthetic_batch(0, CFG)
    _, metrics = loss.loss_fn(params, batch, None, CFG)
    out = jax.tree.map(
        lambda x: np.asarray(x, np.float64),
        model.filter_sequence(params, batch["camera"], batch["lidar"], batch["action"], None, CFG),
    )
    b = batch["camera"].shape[0]
    kl = np_kl(out["q_grid_loc"], out["q_grid_scale"], out["p_grid_loc"], out["p_grid_scale"])
    np.testing.assert_allclose(metrics["kl_grid"], kl.sum() / b, rtol=2e-4)
    np.testing.assert_array_equal(out["p_grid_loc"][:, 0], 0.0)
    np.testing.assert_array_equal(out["p_grid_scale"][:, 0], 1.0)
    pose = np.asarray(batch["pose"], np.float64)
    yaw = np.arctan2(pose[..., 3], pose[..., 2])
    d = pose[:, 1:, :2] - pose[:, :-1, :2]
    c, s = np.cos(yaw[:, :-1]), np.sin(yaw[:, :-1])
    dyaw = np.angle(np.exp(1j * (yaw[:, 1:] - yaw[:, :-1])))
    truth = np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1], dyaw], -1)
    error = (out["motion"][:, 1:] - truth) / [1.0, 0.1, 0.02]
    np.testing.assert_allclose(metrics["motion"], 32.0 * np.sum(0.5 * error**2) / b, rtol=2e-4)


@pytest.mark.slow
@pytest.mark.parametrize(
    "grid_warp, grid_motion, memory",
    [("bilinear", "ego", 0), ("lattice", "ego", 0), ("lattice", "ego_and_carried_flow", 4)],
)
def test_streaming_the_grid_equals_the_training_scan(params, grid_warp, grid_motion, memory):
    """filter_step frame by frame (the grid in the state) gives filter_sequence's grid, with sampled latents
    (each frame's key as the scan splits it; the means are the same code with no key). On the lattice the
    state carries the lattice's grid and offset (and a carried flow its flow and lidar map, a memory its
    channels after the sample's), and :func:`model.end_state` of the scan is the streamed state."""
    cfg = config_lib.replace(CFG, model=dict(grid_warp=grid_warp, grid_motion=grid_motion, grid_memory_channels=memory))
    if grid_motion != "ego" or memory:
        params = model.init_params(jax.random.PRNGKey(0), cfg)
    batch = synthetic_batch(1, cfg)
    key = jax.random.PRNGKey(3)
    scanned = model.filter_sequence(params, batch["camera"], batch["lidar"], batch["action"], key, cfg)
    t1 = batch["camera"].shape[1]
    keys = jax.random.split(key, t1)
    state, step = model.init_filter_state(batch["camera"].shape[0], cfg), jax.jit(model.filter_step, static_argnums=6)
    prev_action = jnp.concatenate([jnp.zeros_like(batch["action"][:, :1]), batch["action"][:, :-1]], 1)
    for t in range(t1):
        state, out = step(params, state, batch["camera"][:, t], batch["lidar"][:, t], prev_action[:, t], keys[t], cfg)
        np.testing.assert_allclose(out["grid"], scanned["grid"][:, t], rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(out["z1"], scanned["z1"][:, t], rtol=1e-4, atol=1e-4)
    assert state.grid.shape == (batch["camera"].shape[0], 16, 16, cfg.model.grid_channels + memory)
    ended, _ = model.end_state(scanned, batch["action"])
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4), state, ended)
    if grid_warp == "lattice":
        offset = np.asarray(state.grid_offset)
        assert offset.shape == (batch["camera"].shape[0], 2) and np.all(np.abs(offset) <= 1.0 + 1e-5)
        np.testing.assert_allclose(bev_latent.shift(state.grid, -state.grid_offset), out["grid"], atol=1e-5)


def test_the_grids_memory_reads_the_frame_only_through_the_motion_that_carries_it():
    """With a memory per cell (``--model.grid_memory_channels``) the prior reads the memory, so the memory of
    frame t may depend on frame t only through the ego's motion that warps it: with the motion head's output
    held at zero, two different frames after the same state give the same memory channels and different
    samples (the posterior's means, no key), while a different carried state changes the memory."""
    cfg = config_lib.replace(CFG, model=dict(grid_memory_channels=4))
    params = model.init_params(jax.random.PRNGKey(0), cfg)
    head = params["params"]["motion_head"]
    last = sorted(head)[-1]
    params["params"]["motion_head"] = {**head, last: jax.tree.map(jnp.zeros_like, head[last])}
    batch = synthetic_batch(1, cfg)
    camera, lidar, action = batch["camera"], batch["lidar"], batch["action"]
    state = model.init_filter_state(camera.shape[0], cfg)
    state, _ = model.filter_step(params, state, camera[:, 0], lidar[:, 0], action[:, 0], None, cfg)
    c = cfg.model.grid_channels
    _, seen = model.filter_step(params, state, camera[:, 1], lidar[:, 1], action[:, 0], None, cfg)
    _, other = model.filter_step(params, state, 255 - camera[:, 1], 255 - lidar[:, 1], action[:, 0], None, cfg)
    np.testing.assert_array_equal(seen["grid"][..., c:], other["grid"][..., c:])
    assert np.abs(np.asarray(seen["grid"][..., :c] - other["grid"][..., :c])).max() > 1e-3
    moved = state.replace(grid=state.grid + 1.0)
    _, carried = model.filter_step(params, moved, camera[:, 1], lidar[:, 1], action[:, 0], None, cfg)
    assert np.abs(np.asarray(carried["grid"][..., c:] - seen["grid"][..., c:])).max() > 1e-3


@pytest.mark.slow
def test_the_readmes_example_runs_as_written_with_the_grid(tmp_path):
    """The README's inference example on a trained run with the bird-eye latent: its state carries the grid."""
    cfg = config_lib.replace(CFG, train=dict(num_steps=2, checkpoint_every=2, log_every=1))
    train_lib.train(cfg, str(tmp_path))
    names = run_readme_example(tmp_path, cfg)
    assert names["state"].grid.shape == (4, 16, 16, cfg.model.grid_channels)
    assert np.isfinite(np.asarray(names["state"].grid)).all()


def _lidar_with(points_m, image_size=64):
    """A lidar image uint8 [1, R, R, 3] with an obstacle return (green) at each ego-frame point [M, 2] (m)."""
    image = np.zeros((1, image_size, image_size, 3), np.uint8)
    row, col = np.floor(np.asarray(geo.ego_to_bev_px(np.asarray(points_m, np.float32), image_size))).astype(int).T
    image[0, row, col, 1] = 255
    return image


def _shadowed_by_ray_march(image, margin_m):
    """bool [R, R]: pixels whose centre lies more than ``margin_m`` behind an obstacle pixel that the straight
    segment from the ego to that centre crosses (the segment against each obstacle square, by slab clipping)."""
    r = image.shape[1]
    res = geo.bev_metres_per_px(r)
    centres = np.asarray(geo.bev_pixel_centres(r, np), np.float64)
    shadowed = np.zeros((r, r), bool)
    for orow, ocol in zip(*np.nonzero(image[0, ..., 1])):
        lo, hi = centres[orow, ocol] - res / 2, centres[orow, ocol] + res / 2  # the square's x and y extents
        with np.errstate(divide="ignore", invalid="ignore"):
            t_lo, t_hi = lo / centres, hi / centres  # where the segment t * centre, t in [0, 1], meets each slab
        enter = np.nanmax(np.minimum(t_lo, t_hi), -1)
        leave = np.nanmin(np.maximum(t_lo, t_hi), -1)
        crosses = (enter <= leave) & (leave >= 0) & (enter <= 1)
        obstacle_m = np.hypot(*centres[orow, ocol])
        shadowed |= crosses & (np.hypot(centres[..., 0], centres[..., 1]) > obstacle_m + margin_m)
    return shadowed


def test_the_lidar_sees_every_cell_of_an_empty_view_and_none_behind_a_wall():
    np.testing.assert_array_equal(bev_latent.lidar_visibility(np.zeros((2, 64, 64, 3), np.uint8), 16), 1.0)
    across = np.stack([np.full(64, 9.9), np.linspace(-15.9, 15.9, 64)], -1)  # a wall 9.9 m ahead, view-wide
    seen = np.asarray(bev_latent.lidar_visibility(_lidar_with(across), 16))[0, ..., 0]
    cell_ahead_m = 20.0 - 2.0 * (np.arange(16) + 1)  # the near edge of each row of 2 m cells
    np.testing.assert_array_equal(seen[cell_ahead_m >= 9.9 + 2.0], 0.0)  # wholly over a metre behind the wall
    np.testing.assert_array_equal(seen[cell_ahead_m + 2.0 <= 9.9], 1.0)  # wholly before it


def test_a_parked_car_shadows_the_cells_behind_it_and_no_others():
    """A car's face 8 m ahead (returns across 2 m): the cell 16 m straight behind it is unseen, the cells at
    its side, before it, and behind the ego are seen; pixel by pixel the shadow agrees with a ray march."""
    face = np.stack([np.full(9, 8.0), np.linspace(-1.0, 1.0, 9)], -1)
    image = _lidar_with(face)
    cells = np.asarray(bev_latent.lidar_visibility(image, 16))[0, ..., 0]
    cell = lambda x_m, y_m: cells[tuple(np.floor(np.asarray(geo.ego_to_bev_px(np.array([x_m, y_m]), 16))).astype(int))]
    assert cell(17.0, 0.0) == 0.0
    assert cell(17.0, 10.0) == cell(4.0, 0.0) == cell(-8.0, 0.0) == 1.0
    pixels = ~np.asarray(bev_latent.lidar_visibility(image, 64))[0, ..., 0].astype(bool)
    marched = _shadowed_by_ray_march(image, bev_latent.SHADOW_MARGIN_M)
    assert np.all(pixels[marched])  # every pixel a ray march finds behind the car is shadowed
    # and the bins (1 degree, each pixel's half-diagonal either side) widen it by at most 15 %
    assert (pixels & ~marched).sum() <= 0.15 * marched.sum()
    assert bev_latent.VISIBILITY_BINS == sensors.LIDAR_NUM_AZIMUTHS


def test_the_gated_update_moves_from_the_prior_by_the_share_seen():
    prior, posterior = (np.array([1.0, -2.0]), np.array([0.5, 2.0])), (np.array([3.0, 0.0]), np.array([2.0, 0.5]))
    for share, loc, scale in [(0.0, prior[0], prior[1]), (1.0, *posterior), (0.5, [2.0, -1.0], [1.0, 1.0])]:
        np.testing.assert_allclose(model.gated_update(prior, posterior, share), (loc, scale), rtol=1e-6)


def test_the_fused_update_is_the_normalised_product_of_the_prior_and_the_weighted_observation():
    """Against the densities themselves: log N(x; fused) - log N(x; prior) - share * log N(x; observation) is
    the same at every x (the product, normalised); no share gives the prior bit for bit, and the scale never
    grows."""
    rng = np.random.default_rng(0)
    prior = (rng.normal(size=6).astype(np.float32), rng.uniform(0.1, 3.0, 6).astype(np.float32))
    observation = (rng.normal(size=6).astype(np.float32), rng.uniform(0.1, 3.0, 6).astype(np.float32))
    share = np.array([0.0, 0.1, 0.5, 1.0, 0.3, 1.0])
    loc, scale = (np.asarray(v, np.float64) for v in model.fused_update(prior, observation, share))
    x = np.linspace(-5.0, 5.0, 41)[:, None]
    log_normal = lambda loc, scale: -0.5 * ((x - loc) / scale) ** 2 - np.log(scale)
    gap = log_normal(loc, scale) - log_normal(*prior) - share * log_normal(*observation)  # [x, 6]
    np.testing.assert_allclose(gap - gap[:1], 0.0, atol=1e-4)
    np.testing.assert_array_equal(np.asarray(model.fused_update(prior, observation, 0.0)), np.asarray(prior))
    assert np.all(scale <= prior[1] + 1e-7)


@pytest.mark.slow
@pytest.mark.parametrize("grid_update", ["lidar_gated", "lidar_fused"])
def test_a_gated_grid_keeps_its_prior_in_every_cell_the_lidar_cannot_see(grid_update):
    """With ``grid_update="lidar_gated"`` (or ``"lidar_fused"``) the posterior of a cell behind a wall is its
    prior exactly (KL zero); in a cell the lidar sees whole, it is the learned posterior of the ungated model
    (whose parameters are the same), or its product with the prior."""
    gated = config_lib.replace(CFG, model=dict(grid_update=grid_update))
    params = model.init_params(jax.random.PRNGKey(0), gated)
    batch = synthetic_batch(0, gated)
    r = gated.data.image_size
    across = np.stack([np.full(r, 3.9), np.linspace(-15.9, 15.9, r)], -1)
    lidar = np.broadcast_to(_lidar_with(across, r), batch["lidar"].shape)
    run = lambda cfg: model.filter_sequence(params, batch["camera"], lidar, batch["action"], None, cfg)
    out, plain = run(gated), run(CFG)
    g = gated.model.grid_cells
    behind = np.asarray(bev_latent.lidar_visibility(lidar[:1, 0], g))[0, ..., 0] == 0.0
    assert behind.any() and (~behind).any()
    for name in ("loc", "scale"):
        q, p = np.asarray(out[f"q_grid_{name}"])[:, 1:], np.asarray(out[f"p_grid_{name}"])[:, 1:]
        np.testing.assert_array_equal(q[:, :, behind], p[:, :, behind])
    seen = np.asarray(bev_latent.lidar_visibility(lidar[:1, 0], g))[0, ..., 0] == 1.0
    expected = plain["q_grid_loc"][:, 0]
    if grid_update == "lidar_fused":  # a first frame's prior is N(0, I)
        expected = model.fused_update((0.0, 1.0), (plain["q_grid_loc"][:, 0], plain["q_grid_scale"][:, 0]), 1.0)[0]
    np.testing.assert_allclose(out["q_grid_loc"][:, 0][:, seen], np.asarray(expected)[:, seen], rtol=1e-5, atol=1e-6)


def _decoder_inputs(seed=0):
    """A filter's outputs for :func:`model.decode` at ``CFG``'s sizes: random z1, z2 and grid for 2 frames."""
    m, g = CFG.model, CFG.model.grid_cells
    rng = np.random.default_rng(seed)
    z1, z2 = (rng.normal(size=(2, d)).astype(np.float32) for d in (m.z1_dim, m.z2_dim))
    grid = rng.normal(size=(2, g, g, m.grid_channels)).astype(np.float32)
    return {"z1": z1, "z2": z2, "features": None, "grid": grid}


def test_the_pixor_decoder_reads_the_grid_alone_when_asked(params):
    """``detection_input="grid"``: the PIXOR maps are the latent decoder's (same parameters) at z = 0, so no z
    moves them and the grid does; the lidar and roadmap decoders still read z beside the grid."""
    grid_only = config_lib.replace(CFG, model=dict(detection_input="grid"))
    filtered = _decoder_inputs()
    z1, z2, grid = filtered["z1"], filtered["z2"], filtered["grid"]
    got = model.decode(params, filtered, grid_only)
    zeros = model.decode(params, dict(filtered, z1=0 * z1, z2=0 * z2), CFG)
    np.testing.assert_allclose(got["det_logit"], zeros["det_logit"], rtol=1e-5, atol=1e-6)
    other_z = model.decode(params, dict(filtered, z1=-z1, z2=-z2), grid_only)
    np.testing.assert_array_equal(other_z["det_logit"], got["det_logit"])
    assert not np.allclose(other_z["lidar"], got["lidar"], atol=1e-3)
    other_grid = model.decode(params, dict(filtered, grid=-grid), grid_only)
    assert not np.allclose(other_grid["det_logit"], got["det_logit"], atol=1e-3)
    with pytest.raises(ValueError, match="--model.detection_input=grid"):
        config_lib.validate(config_lib.replace(TINY, model=dict(detection_input="grid")))


def test_the_lidar_decoder_reads_z_alone_when_asked():
    """``lidar_decoder_input="latent"``: the lidar image no longer moves with the grid, the PIXOR and roadmap maps
    still do; the lidar decoder's parameters are then shaped as the camera decoder's (no grid channels joined)."""
    apart = config_lib.replace(CFG, model=dict(lidar_decoder_input="latent"))
    params = model.init_params(jax.random.PRNGKey(0), apart)
    filtered = _decoder_inputs()
    z1, z2, grid = filtered["z1"], filtered["z2"], filtered["grid"]
    got = model.decode(params, filtered, apart)
    other_grid = model.decode(params, dict(filtered, grid=-grid), apart)
    np.testing.assert_array_equal(other_grid["lidar"], got["lidar"])
    for moved in ("det_logit", "roadmap"):
        assert not np.allclose(other_grid[moved], got[moved], atol=1e-3), moved
    other_z = model.decode(params, dict(filtered, z1=-z1, z2=-z2), apart)
    assert not np.allclose(other_z["lidar"], got["lidar"], atol=1e-3)
    decoders = params["params"]
    shapes = lambda name: jax.tree.map(np.shape, decoders[name])
    assert shapes("image_decoders_lidar") == shapes("image_decoders_camera")
    assert shapes("image_decoders_roadmap") != shapes("image_decoders_camera")
    with pytest.raises(ValueError, match="--model.lidar_decoder_input='latent' keeps the bird-eye grid"):
        config_lib.validate(config_lib.replace(TINY, model=dict(lidar_decoder_input="latent")))
