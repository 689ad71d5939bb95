"""The town against independent truth: graph search, raster look-ups and geometry done here, not in town.py."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from e2e_percep_jax.config import DEFAULT_TOWN_SEED
from e2e_percep_jax.sim import extent
from e2e_percep_jax.sim import town as town_lib

HELD_OUT_SEED = 1
DRIVABLE = [town_lib.SEM_ROAD, town_lib.SEM_LANE_WHITE, town_lib.SEM_CENTRE_YELLOW, town_lib.SEM_STOP_LINE]


@pytest.fixture(scope="module", params=[DEFAULT_TOWN_SEED, HELD_OUT_SEED], ids=["default", "held_out"])
def town(request):
    return jax.tree.map(np.asarray, town_lib.build_town(request.param))


def sem_at(town, xy):
    """Semantic class of the map cell under town points ``xy`` [..., 2] (the cell convention of Town's docs)."""
    col, row = np.moveaxis(np.floor((xy - town.map_origin_m) / town.map_res_m).astype(int), -1, 0)
    assert (row >= 0).all() and (row < town.sem_map.shape[0]).all() and (col >= 0).all()
    assert (col < town.sem_map.shape[1]).all()
    return town.sem_map[row, col]


def lane_samples(town, lane):
    """The stored samples of ``lane`` up to its end, plus the end itself (xy [M, 2], yaw [M])."""
    pos = town.lane_length_m[lane] / town_lib.LANE_DS_M
    m = int(np.floor(pos))
    end_xy = town.lane_xy_m[lane, m] + (pos - m) * (town.lane_xy_m[lane, m + 1] - town.lane_xy_m[lane, m])
    return (
        np.concatenate([town.lane_xy_m[lane, : m + 1], end_xy[None]]),
        np.append(town.lane_yaw_rad[lane, : m + 1], town.lane_yaw_rad[lane, m]),
    )


def reachable(adjacency, start):
    """Breadth-first search over a boolean adjacency matrix."""
    seen = np.zeros(len(adjacency), bool)
    seen[start] = True
    frontier = seen.copy()
    while frontier.any():
        frontier = adjacency[frontier].any(0) & ~seen
        seen |= frontier
    return seen


def test_every_lane_has_a_successor_and_the_graph_is_strongly_connected(town):
    nl = len(town.lane_length_m)
    succ = town.lane_succ
    assert (town.lane_num_succ >= 1).all()
    assert all((succ[i, :k] >= 0).all() and (succ[i, k:] == -1).all() for i, k in enumerate(town.lane_num_succ))
    adjacency = np.zeros((nl, nl), bool)
    rows, cols = np.nonzero(succ >= 0)
    adjacency[rows, succ[rows, cols]] = True
    assert reachable(adjacency, 0).all(), "some lane cannot be reached from lane 0"
    assert reachable(adjacency.T, 0).all(), "lane 0 cannot be reached from some lane"


def test_successors_continue_where_their_lane_ends(town):
    """The graph agrees with the geometry: a successor starts at its predecessor's end, heading the same way."""
    for lane in range(len(town.lane_length_m)):
        end_xy, end_yaw = (a[-1] for a in lane_samples(town, lane))
        for nxt in town.lane_succ[lane, : town.lane_num_succ[lane]]:
            assert np.linalg.norm(town.lane_xy_m[nxt, 0] - end_xy) < 0.1, (lane, nxt)
            turn = (town.lane_yaw_rad[nxt, 0] - end_yaw + np.pi) % (2 * np.pi) - np.pi
            assert abs(turn) < 0.15, (lane, nxt, turn)


def test_lane_centres_and_a_car_width_around_them_are_drivable(town):
    for lane in range(len(town.lane_length_m)):
        xy, yaw = lane_samples(town, lane)
        left = np.stack([-np.sin(yaw), np.cos(yaw)], -1)
        for offset_m in (0.0, -1.0, 1.0):  # centre, and the sides of a 2 m wide car
            sem = sem_at(town, xy + offset_m * left)
            assert np.isin(sem, DRIVABLE).all(), (lane, offset_m, xy[~np.isin(sem, DRIVABLE)][:3])


def test_buildings_stand_off_the_road_and_sidewalk(town):
    u = np.linspace(-0.5, 0.5, 9)
    grid = np.stack(np.meshgrid(u, u, indexing="ij"), -1).reshape(-1, 2)  # unit square, edges included
    for x, y, yaw, length, width in town.building_box:
        local = grid * [length, width]
        c, s = np.cos(yaw), np.sin(yaw)
        pts = np.stack([x + c * local[:, 0] - s * local[:, 1], y + s * local[:, 0] + c * local[:, 1]], -1)
        assert (sem_at(town, pts) == town_lib.SEM_OFFROAD).all(), (x, y)
    assert len(town.building_box) > 100
    # Varied: footprints, heights and colours spread.
    assert np.ptp(town.building_box[:, 3] * town.building_box[:, 4]) > 100.0
    assert np.ptp(town.building_height_m) > 20.0
    assert len(np.unique(town.building_color, axis=0)) > 50


def test_every_lane_lies_inside_the_towns_square_with_room_to_spare(town):
    """The square the pose belief's grid covers (extent.AREA_*), derived from the node grid: every lane sample
    (extended past a lane's end as stored) lies 10 m or more inside it, and the square is no more than the
    lanes' extent and the building belt."""
    xy = town.lane_xy_m.reshape(-1, 2)
    lo, hi = extent.AREA_ORIGIN_M, extent.AREA_ORIGIN_M + extent.AREA_SIZE_M
    assert (xy.min(0) >= lo + 10.0).all() and (xy.max(0) <= hi - 10.0).all(), (xy.min(0), xy.max(0))
    assert (xy.min(0) <= lo + extent.BUILDING_BELT_M + 10.0).all()
    assert (xy.max(0) >= hi - extent.BUILDING_BELT_M - 10.0).any()


def test_size_and_road_length_are_like_town03(town):
    lo, hi = town.node_xy_m.min(0), town.node_xy_m.max(0)
    assert ((hi - lo > 350) & (hi - lo < 450)).all(), hi - lo
    road_km = np.linalg.norm(town.road_xy_m[:, 1] - town.road_xy_m[:, 0], axis=1).sum() / 1000
    assert 5.0 < road_km < 7.0, road_km
    # The raster agrees: road area ~ length x width of the carriageways (junction squares make it larger).
    road_cells = np.isin(town.sem_map, DRIVABLE).sum() * town.map_res_m**2
    carriageway_m2 = (
        np.linalg.norm(town.road_xy_m[:, 1] - town.road_xy_m[:, 0], axis=1)
        * 2
        * town.road_lanes_per_dir
        * town_lib.LANE_WIDTH_M
    ).sum()
    assert 0.8 < road_cells / carriageway_m2 < 1.3, road_cells / carriageway_m2


def test_roads_are_two_way_and_some_have_two_lanes_per_direction(town):
    """Counts, for each road, the road lanes alongside it in each direction from their own geometry."""
    road_lanes = np.flatnonzero(town.lane_kind == town_lib.LANE_ROAD)
    start = town.lane_xy_m[road_lanes, 0]
    mid = start + 0.5 * (town.lane_xy_m[road_lanes, np.floor(town.lane_length_m[road_lanes]).astype(int)] - start)
    heading = np.stack([np.cos(town.lane_yaw_rad[road_lanes, 0]), np.sin(town.lane_yaw_rad[road_lanes, 0])], -1)
    for (a, b), per_dir in zip(town.road_xy_m, town.road_lanes_per_dir):
        along = (b - a) / np.linalg.norm(b - a)
        rel = mid - 0.5 * (a + b)  # lane middles sit near the road's middle (mouths differ at either end)
        lateral_m = rel @ [-along[1], along[0]]
        alongside = (np.abs(rel @ along) < 0.2 * np.linalg.norm(b - a)) & (
            np.abs(lateral_m) < 2 * town_lib.LANE_WIDTH_M
        )
        forward = alongside & (heading @ along > 0.99)
        backward = alongside & (heading @ along < -0.99)
        assert forward.sum() == per_dir and backward.sum() == per_dir, (a, b, forward.sum(), backward.sum())
    assert (town.road_lanes_per_dir == 2).sum() >= 4
    assert (town.road_lanes_per_dir == 1).sum() >= 4


def test_three_and_four_way_junctions_and_a_roundabout(town):
    ends = town.road_xy_m.reshape(-1, 2)
    degree = (np.linalg.norm(ends[:, None] - town.node_xy_m[None], axis=-1) < 1e-3).sum(0)
    np.testing.assert_array_equal(degree, town.node_degree)
    assert (degree == 3).sum() >= 3 and (degree == 4).sum() >= 3
    rings = np.flatnonzero(town.node_kind == town_lib.NODE_ROUNDABOUT)
    assert len(rings) >= 1
    centre = town.node_xy_m[rings[0]]
    ring_lanes = np.flatnonzero(town.lane_kind == town_lib.LANE_RING)
    assert len(ring_lanes) >= 2 * degree[rings[0]]  # cut at every entry and exit
    for lane in ring_lanes:
        xy, yaw = lane_samples(town, lane)
        np.testing.assert_allclose(np.linalg.norm(xy - centre, axis=1), town.ring_radius_m, atol=0.05)
        radial = (xy - centre) / np.linalg.norm(xy - centre, axis=1, keepdims=True)
        assert (radial[:, 0] * np.sin(yaw) - radial[:, 1] * np.cos(yaw) > 0.95).all()  # counter-clockwise
    # Following ring successors goes round once and comes back.
    lane, seen = ring_lanes[0], []
    while lane not in seen:
        seen.append(lane)
        lane = next(s for s in town.lane_succ[lane] if s in ring_lanes)
    assert sorted(seen) == sorted(ring_lanes)
    assert sem_at(town, centre) == town_lib.SEM_OFFROAD  # the island
    assert sem_at(town, centre + [town.ring_radius_m, 0.0]) in DRIVABLE


def test_lights_cycle_through_phases_and_never_give_two_approaches_green(town):
    nt = len(town.light_cycle_s)
    assert nt >= 10
    times_s = np.arange(0.0, 2 * town.light_cycle_s.max(), 0.1)
    states = np.stack([np.asarray(town_lib.light_states(town, t)) for t in times_s])  # [T, NT]
    for light in range(nt):
        assert set(np.unique(states[:, light])) == {town_lib.LIGHT_RED, town_lib.LIGHT_YELLOW, town_lib.LIGHT_GREEN}
    for node in np.unique(town.light_node):
        assert town.node_kind[node] == town_lib.NODE_SIGNAL
        mine = town.light_node == node
        assert mine.sum() == town.node_degree[node]  # one light per approach
        assert ((states[:, mine] == town_lib.LIGHT_GREEN).sum(1) <= 1).all(), node
        assert ((states[:, mine] != town_lib.LIGHT_RED).sum(1) <= 1).all(), node  # yellow clears before green
    # Every signalled lane ends at a stop line next to its own junction.
    for lane in np.flatnonzero(town.lane_light >= 0):
        node_xy = town.node_xy_m[town.light_node[town.lane_light[lane]]]
        assert np.linalg.norm(lane_samples(town, lane)[0][-1] - node_xy) < 30.0
        assert lane in town.stop_line_lane


def test_town_is_a_pytree_of_arrays_usable_under_jit():
    town = town_lib.build_town(DEFAULT_TOWN_SEED)
    leaves = jax.tree.leaves(town)
    assert len(leaves) == len(town_lib.Town._fields)
    assert all(isinstance(leaf, jax.Array) for leaf in leaves)
    total = jax.jit(lambda t: jnp.sum(t.lane_length_m))(town)
    np.testing.assert_allclose(total, np.asarray(town.lane_length_m).sum(), rtol=1e-6)


@pytest.mark.slow
def test_same_seed_same_town_and_other_seeds_differ():
    default = town_lib.build_town(DEFAULT_TOWN_SEED)
    rebuilt = town_lib.build_town.__wrapped__(DEFAULT_TOWN_SEED)  # bypass the cache
    for a, b in zip(default, rebuilt):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    other = town_lib.build_town(HELD_OUT_SEED)
    assert not np.allclose(np.asarray(default.node_xy_m), np.asarray(other.node_xy_m))
    assert (
        np.asarray(default.sem_map).shape != np.asarray(other.sem_map).shape
        or (np.asarray(default.sem_map) != np.asarray(other.sem_map)).mean() > 0.05
    )


@pytest.mark.slow
@pytest.mark.parametrize("seed", [DEFAULT_TOWN_SEED, HELD_OUT_SEED, 7])
def test_spawn_slots_from_the_lane_graph_match_the_built_town(seed):
    """The launchers' vehicle-count check reads the lane graph alone; the built town must agree."""
    assert town_lib.spawn_slots(seed) == town_lib.build_town(seed).spawn_lane.shape[0] > 100


def test_a_cached_town_loads_equal_to_the_built_one_and_a_damaged_file_is_built_again(tmp_path, monkeypatch):
    """The town cache (``E2E_PERCEP_JAX_TOWN_CACHE``) round-trips every field exactly, answers
    ``spawn_slots`` without the lane graph, and a file that cannot be read is built again and replaced."""
    monkeypatch.setenv(town_lib.CACHE_ENV, str(tmp_path))
    built = town_lib._town_np(DEFAULT_TOWN_SEED)  # nothing cached yet: built, then written
    (path,) = tmp_path.iterdir()
    assert path.name.startswith(f"town-{DEFAULT_TOWN_SEED}-") and path.suffix == ".npz"
    builds = []
    monkeypatch.setattr(town_lib, "_build_town_np", lambda seed: builds.append(seed) or built)
    monkeypatch.setattr(town_lib, "_lane_graph", None)  # neither the build nor spawn_slots may need it now
    loaded = town_lib._town_np(DEFAULT_TOWN_SEED)
    for name in town_lib.Town._fields:
        a, b = getattr(built, name), getattr(loaded, name)
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), name
    assert town_lib.spawn_slots.__wrapped__(DEFAULT_TOWN_SEED) == len(built.spawn_lane)
    assert builds == []
    path.write_bytes(b"not a zip file")
    assert town_lib._town_np(DEFAULT_TOWN_SEED) is built and builds == [DEFAULT_TOWN_SEED]  # built again
    assert town_lib._read_cached(DEFAULT_TOWN_SEED) is not None  # and the file replaced by a readable one
