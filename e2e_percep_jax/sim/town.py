"""The static town: roads, lanes, junctions, lights, sidewalks, buildings and its semantic raster.

Built once per seed with NumPy (:func:`build_town`, cached), then held as a pytree of arrays (:class:`Town`)
that every pure-JAX world and sensor function takes as a constant argument. A directory named by the
environment variable ``E2E_PERCEP_JAX_TOWN_CACHE`` keeps built towns for other processes (:data:`CACHE_ENV`; the
evaluation keeps its choice of drives there too).

What a town is (all procedural from the seed; right-hand traffic):

- a jittered grid of 8 x 7 nodes about 60 m x 70 m apart (about 420 m square, about 6 km of road) joined by
  two-way roads. One row and one column are arterials with two lanes per direction, the rest have one.
  Lanes are numbered from the yellow centre line outwards (lane 0 is the inner lane). A few interior roads
  are removed, which turns some 4-way junctions into 3-way ones and leaves larger blocks.
- Nodes of degree >= 3 are signalised junctions with split phasing: the approaches get green one at a time
  (then yellow, then all-red), so conflicting movements are never green together. The grid's corners are
  unsignalised bends. One interior node is a one-lane roundabout (counter-clockwise; entries yield to the
  ring).
- Lanes are centre polylines. Road lanes run from junction mouth to junction mouth; connector lanes join an
  incoming lane's end (its stop line) to an outgoing lane's start through the junction, and the roundabout's
  ring is cut into arcs at its entry and exit points. The lane graph is strongly connected (no U-turns).
- Conflict table: for every pair of lanes whose centrelines pass within ``CONFLICT_DIST_M`` of each other
  (and which are not within two hops in the lane graph), the arc interval of each lane that lies that close
  to the other. A vehicle whose body stays outside that interval cannot touch any vehicle on the other lane.
- Buildings and landmarks (buildings, towers, kiosks, trees, poles, a monument in the roundabout) stand on
  offroad cells only, at least ``BUILDING_CLEARANCE_M`` from road and sidewalk.
"""

import functools
import hashlib
import os
import zipfile
from typing import NamedTuple

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax.sim.extent import BUILDING_BELT_M, GRID_NODES, GRID_SPACING_M
from e2e_percep_jax.sim.geometry import wrap_angle

# Semantic classes of ``Town.sem_map`` (and of the roadmap image before colouring).
SEM_OFFROAD = 0  # terrain between roads (buildings stand here)
SEM_ROAD = 1  # drivable asphalt, junctions included
SEM_SIDEWALK = 2
SEM_LANE_WHITE = 3  # dashed white divider between same-direction lanes
SEM_CENTRE_YELLOW = 4  # solid yellow line between opposite directions
SEM_STOP_LINE = 5  # white bar where a lane meets a junction
NUM_SEM_CLASSES = 6

# Roadmap colours per class (RGB), as in the reference's bird-eye view: black terrain, dark road.
SEM_COLORS = np.array(
    [
        [0, 0, 0],  # offroad
        [60, 60, 64],  # road
        [130, 130, 130],  # sidewalk
        [230, 230, 230],  # white lane divider
        [230, 200, 40],  # yellow centre line
        [255, 255, 255],  # stop line
    ],
    dtype=np.uint8,
)

# Lane kinds (``Town.lane_kind``).
LANE_ROAD = 0  # between two junction mouths
LANE_CONNECTOR = 1  # through a signalised junction or a bend
LANE_RING = 2  # an arc of the roundabout's ring
LANE_RING_ENTRY = 3  # from an approach onto the ring (yields to the ring)
LANE_RING_EXIT = 4  # from the ring onto a leaving road

# Node kinds (``Town.node_kind``).
NODE_BEND = 0  # degree 2, unsignalised
NODE_SIGNAL = 1  # degree 3 or 4, traffic lights
NODE_ROUNDABOUT = 2
NODE_PRIORITY = 3  # degree 3 or 4, unsignalised: the through road has right of way, the other road yields

# Right of way of a lane at conflicts (``Town.lane_priority``; higher goes first).
PRIORITY_YIELD = 1  # roundabout entries, minor approaches at priority junctions
PRIORITY_NORMAL = 2  # roads, bends, signalised junctions (the lights separate movements), left turns off a major road
PRIORITY_MAJOR = 3  # the ring and its exits, straight on / right turns along a major road

# Light states returned by :func:`light_states`.
LIGHT_RED, LIGHT_YELLOW, LIGHT_GREEN = 0, 1, 2

# Building kinds (``Town.building_kind``).
BUILDING, TOWER, KIOSK, TREE, POLE, MONUMENT = range(6)
BUILDING_KIND_NAMES = ("building", "tower", "kiosk", "tree", "pole", "monument")

LANE_WIDTH_M = 3.5
SIDEWALK_WIDTH_M = 3.0
LANE_DS_M = 1.0  # spacing of the stored lane samples
MAX_LANE_LENGTH_M = 60.0  # the world packs arc positions into a fixed range
MIN_TURN_RADIUS_M = 11.0  # every lane's curvature stays below 1 / this (the ego can steer down to 8.7 m)
TURN_LAT_ACCEL_MPS2 = 2.5  # connector speed limit: sqrt(this * radius)
LOCAL_SPEED_MPS = 8.3  # 30 km/h
ARTERIAL_SPEED_MPS = 12.0  # 43 km/h
CONFLICT_DIST_M = 3.3  # > 2 x (half width 1.05 + corner bulge on the tightest curve 0.34) + ego tracking slack
GREEN_LOCAL_S, GREEN_ARTERIAL_S, YELLOW_S, ALL_RED_S = 6.0, 10.0, 3.0, 1.0
SIGNAL_SHARE = 0.3  # of interior junctions between local roads; all on an arterial, none on the perimeter
RING_RADIUS_M = 15.0  # centre line of the roundabout's lane
RING_TURN_RADIUS_M = 12.0  # of the turns onto and off the ring
SPAWN_SPACING_M = 12.0  # reset slots on road lanes; > the longest vehicle plus a gap
STOP_BAR_M = 0.5  # depth of a painted stop line
MAP_RES_M = 0.2
MAP_MARGIN_M = 50.0  # offroad beyond the outermost building belt, so sensors at the edge read valid cells
BUILDING_CLEARANCE_M = 1.5  # from any road or sidewalk cell

_NODE_JITTER_M = 5.0
_NUM_REMOVED_ROADS = 5
_DENSE_DS_M = 0.25  # sampling of lane polylines while building


class Town(NamedTuple):
    """A built town. Field names marked (sensors) are relied on by ``sensors.py``: do not rename.

    Shapes: NL lanes with P samples each, MS max successors, MC max conflicts per lane, NT lights, NS stop
    lines, NR roads, NN nodes, NB buildings, NP spawn slots.

    sem_map (sensors): uint8 [Hm, Wm], SEM_* class of each cell. Cell (i, j) has its centre at town
        (x, y) = map_origin_m + ((j + 0.5), (i + 0.5)) * map_res_m, so row index grows with y (north).
    map_origin_m (sensors): float32 [2], town (x, y) of the corner of cell (0, 0).
    map_res_m (sensors): float32 [], metres per cell.
    building_box (sensors): float32 [NB, 5], (x, y, yaw, length, width) of buildings and landmarks.
    building_height_m (sensors): float32 [NB].
    building_color (sensors): uint8 [NB, 3].
    building_kind: int32 [NB], BUILDING / TOWER / KIOSK / TREE / POLE / MONUMENT.

    lane_xy_m: float32 [NL, P, 2], centre line sampled every LANE_DS_M from the lane's start; samples past
        the lane's end continue straight along its last heading (so look-ups a little past the end are sane).
    lane_yaw_rad: float32 [NL, P], heading of the centre line at each sample.
    lane_curv_1pm: float32 [NL, P], signed curvature (1/m, positive turning left) at each sample.
    lane_length_m: float32 [NL].
    lane_succ: int32 [NL, MS], successor lanes, -1 padded. lane_num_succ: int32 [NL], >= 1.
    lane_speed_limit_mps: float32 [NL].
    lane_kind: int32 [NL], LANE_*.
    lane_priority: int32 [NL], right of way at conflicts, PRIORITY_* (higher goes first).
    lane_light: int32 [NL], the light governing the stop line at this lane's end, -1 if none.
    lane_at_mouth: bool [NL], the lane ends where a junction or roundabout (not a bend) begins.
    conf_lane: int32 [NL, MC], lanes in conflict with this one, -1 padded.
    conf_mirror: int32 [NL, MC], index of the same conflict in the other lane's row.
    conf_in_m, conf_out_m: float32 [NL, MC], arc interval of THIS lane within CONFLICT_DIST_M of the other.
    conf_by_priority: bool [NL, MC], the conflict is resolved by right of way (crossing or merging); False for
        lanes that leave the same lane (diverging), where the vehicle ahead simply goes first.
    light_cycle_s, light_green_start_s, light_green_s: float32 [NT], timing (see :func:`light_states`).
    light_node: int32 [NT], the junction a light belongs to. light_xy_m: float32 [NT, 2], where it stands.
    stop_line_m: float32 [NS, 2, 2], the two ends of each stop (or roundabout yield) line, one per lane.
    stop_line_lane: int32 [NS], the lane that ends at it. stop_line_light: int32 [NS], -1 for yield lines.
    road_xy_m: float32 [NR, 2, 2], node-centre to node-centre segment of each road (its centre line).
    road_lanes_per_dir: int32 [NR].
    node_xy_m: float32 [NN, 2]. node_kind: int32 [NN], NODE_*. node_degree: int32 [NN].
    ring_radius_m: float32 [], radius of the roundabout lane's centre line.
    spawn_lane: int32 [NP], spawn_s_m: float32 [NP], reset slots (SPAWN_SPACING_M apart, bodies on the lane).
    """

    sem_map: np.ndarray
    map_origin_m: np.ndarray
    map_res_m: np.ndarray
    building_box: np.ndarray
    building_height_m: np.ndarray
    building_color: np.ndarray
    building_kind: np.ndarray
    lane_xy_m: np.ndarray
    lane_yaw_rad: np.ndarray
    lane_curv_1pm: np.ndarray
    lane_length_m: np.ndarray
    lane_succ: np.ndarray
    lane_num_succ: np.ndarray
    lane_speed_limit_mps: np.ndarray
    lane_kind: np.ndarray
    lane_priority: np.ndarray
    lane_light: np.ndarray
    lane_at_mouth: np.ndarray
    conf_lane: np.ndarray
    conf_mirror: np.ndarray
    conf_in_m: np.ndarray
    conf_out_m: np.ndarray
    conf_by_priority: np.ndarray
    light_cycle_s: np.ndarray
    light_green_start_s: np.ndarray
    light_green_s: np.ndarray
    light_node: np.ndarray
    light_xy_m: np.ndarray
    stop_line_m: np.ndarray
    stop_line_lane: np.ndarray
    stop_line_light: np.ndarray
    road_xy_m: np.ndarray
    road_lanes_per_dir: np.ndarray
    node_xy_m: np.ndarray
    node_kind: np.ndarray
    node_degree: np.ndarray
    ring_radius_m: np.ndarray
    spawn_lane: np.ndarray
    spawn_s_m: np.ndarray


def light_states(town: Town, time_s):
    """State of every light at ``time_s`` (scalar): int32 [NT] of LIGHT_RED / LIGHT_YELLOW / LIGHT_GREEN.

    Each light is green for ``light_green_s`` from ``light_green_start_s`` (mod its junction's cycle), then
    yellow for YELLOW_S, then red until its turn comes again (the all-red ALL_RED_S included).
    """
    phase_s = jnp.mod(time_s - town.light_green_start_s, town.light_cycle_s)
    return jnp.where(
        phase_s < town.light_green_s,
        LIGHT_GREEN,
        jnp.where(phase_s < town.light_green_s + YELLOW_S, LIGHT_YELLOW, LIGHT_RED),
    ).astype(jnp.int32)


# A directory for built towns, one ``.npz`` per seed and version of the code that builds them: a process
# that finds its town there loads it (milliseconds) instead of building it (seconds). Off unless set; the
# test suite sets it, and a sweep's runs or a cluster's processes may share one.
CACHE_ENV = "E2E_PERCEP_JAX_TOWN_CACHE"


@functools.lru_cache(maxsize=8)
def build_town(seed: int) -> Town:
    """Builds (once per seed, then cached) the town of ``seed``: a Town of jax arrays."""
    return jax.device_put(_town_np(seed))


@functools.lru_cache(maxsize=8)
def spawn_slots(seed: int) -> int:
    """How many vehicles the town of ``seed`` can place at a reset (NumPy only: nothing is compiled). From
    a cached town, or else the lane graph alone, a sixth of the time of building the whole town; once per
    seed (every launcher's checks ask, several times)."""
    cached = _read_cached(seed, fields=("spawn_lane",))
    if cached is not None:
        return len(cached["spawn_lane"])
    *_, lanes, _, _ = _lane_graph(seed)[0]
    return len(_spawn_slots(lanes, _lane_lengths(lanes)))


@functools.lru_cache(maxsize=1)
def _code_digest() -> str:
    """What a cached town depends on besides its seed: this module, the geometry it imports, NumPy's and
    OpenCV's versions (a change to any builds the town anew, under another name)."""
    digest = hashlib.sha256(f"{np.__version__} {cv2.__version__}".encode())
    for module in (__file__, os.path.join(os.path.dirname(__file__), "geometry.py")):
        with open(module, "rb") as f:
            digest.update(f.read())
    return digest.hexdigest()[:16]


def cache_file(name: str) -> str | None:
    """Where ``CACHE_ENV``'s directory keeps ``name`` (None when it is not set)."""
    directory = os.environ.get(CACHE_ENV)
    return os.path.join(directory, name) if directory else None


def write_cached(path: str, arrays: dict) -> None:
    """``arrays`` into the .npz file ``path``, renamed into place when complete: a reader never sees half a
    file."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    partial = f"{path}.{os.getpid()}.partial"
    with open(partial, "wb") as f:
        np.savez(f, **arrays)
    os.replace(partial, path)


def _cache_path(seed: int) -> str | None:
    return cache_file(f"town-{seed}-{_code_digest()}.npz")


def _read_cached(seed: int, fields=Town._fields) -> dict | None:
    """``fields`` of the cached town of ``seed`` as NumPy arrays, or None (no cache, or an unreadable file)."""
    path = _cache_path(seed)
    if path is None or not os.path.exists(path):
        return None
    try:
        with np.load(path) as f:
            return {k: f[k] for k in fields}
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):  # damaged: built again and replaced
        return None


def _town_np(seed: int) -> Town:
    """The town of ``seed`` in NumPy arrays: from the cache if it holds it, else built (and cached if named)."""
    cached = _read_cached(seed)
    if cached is not None:
        return Town(**cached)
    town, path = _build_town_np(seed), _cache_path(seed)
    if path:
        write_cached(path, town._asdict())
    return town


# ----------------------------------------------------------------------------- geometry helpers


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _right_of(heading):
    """Unit vector 90 degrees clockwise of ``heading`` (the right-hand side when driving along it)."""
    return np.stack([heading[..., 1], -heading[..., 0]], -1)


def _angle(v):
    return np.arctan2(v[..., 1], v[..., 0])


def _resample(pts, ds):
    """Resamples a polyline [M, 2] at uniform arc spacing ``ds``; the last sample is the exact end point."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(np.ceil(s[-1] / ds)), 1)
    grid = np.linspace(0.0, s[-1], n + 1)
    return np.stack([np.interp(grid, s, pts[:, 0]), np.interp(grid, s, pts[:, 1])], -1)


def _bezier(p0, h0, p3, h3):
    """Dense cubic Bezier from ``p0`` heading ``h0`` to ``p3`` heading ``h3`` (unit vectors).

    Control arms follow the circular-arc approximation for the turn angle, so a symmetric turn is close to
    a circle (the curve of least peak curvature between the two tangents).
    """
    theta = abs(wrap_angle(_angle(h3) - _angle(h0)))
    chord = np.linalg.norm(p3 - p0)
    arm = chord / 3 if theta < 0.05 else 4 / 3 * np.tan(theta / 4) * chord / (2 * np.sin(theta / 2))
    t = np.linspace(0.0, 1.0, 400)[:, None]
    p1, p2 = p0 + arm * h0, p3 - arm * h3
    pts = (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * p1 + 3 * (1 - t) * t**2 * p2 + t**3 * p3
    return _resample(pts, _DENSE_DS_M)


def _arc(centre, radius, a0, a1):
    """Dense counter-clockwise circular arc from angle ``a0`` to ``a1`` (radians, a1 > a0)."""
    n = max(int(np.ceil(radius * (a1 - a0) / _DENSE_DS_M)), 2)
    a = np.linspace(a0, a1, n + 1)
    return centre + radius * np.stack([np.cos(a), np.sin(a)], -1)


def _fillet(p0, h0, p3, h3):
    """Dense turn from ``p0`` heading ``h0`` to ``p3`` heading ``h3``: straight, circular arc, straight.

    The arc is the largest that fits tangent to both lane lines (its radius is set by the shorter of the two
    distances to where the lines cross), so the turn is as gentle as the junction allows.
    """
    t, u = np.linalg.solve(np.stack([h0, h3], 1), p3 - p0)  # p0 + t h0 == p3 - u h3 is where the lines cross
    theta = wrap_angle(_angle(h3) - _angle(h0))  # > 0 turning left
    tangent = min(t, u)
    radius = tangent / np.tan(abs(theta) / 2)
    a = p0 + (t - tangent) * h0  # where the arc starts
    normal = np.array([-h0[1], h0[0]]) * np.sign(theta)  # towards the arc's centre
    centre = a + radius * normal
    a0 = _angle(a - centre)
    n = max(int(np.ceil(radius * abs(theta) / _DENSE_DS_M)), 2)
    angles = a0 + np.linspace(0.0, theta, n + 1)
    arc = centre + radius * np.stack([np.cos(angles), np.sin(angles)], -1)
    return _resample(np.concatenate([p0[None], arc, p3[None]]), _DENSE_DS_M)


def _yaw_and_curvature(pts):
    """Heading [M] (unwrapped) and signed curvature [M] of a uniformly resampled dense polyline."""
    d = np.gradient(pts, axis=0)
    yaw = np.unwrap(_angle(d))
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    curv = np.gradient(yaw, s) if len(pts) > 2 else np.zeros(len(pts))
    return yaw, curv


# ----------------------------------------------------------------------------- road network


def _road_network(rng):
    """Nodes, roads and the roundabout of a jittered grid.

    Returns (node_xy [NN, 2], roads [NR, 2] int node pairs, lanes_per_dir [NR], ring_node, interior [NN]).
    """
    nx, ny = GRID_NODES
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    node_xy = np.stack([ii * GRID_SPACING_M[0], jj * GRID_SPACING_M[1]], -1).reshape(-1, 2).astype(float)
    node_xy += rng.uniform(-_NODE_JITTER_M, _NODE_JITTER_M, node_xy.shape)
    node = lambda i, j: i * ny + j
    arterial_col, arterial_row = rng.integers(2, nx - 2), rng.integers(2, ny - 2)
    roads, lanes = [], []
    for i in range(nx):
        for j in range(ny):
            if i + 1 < nx:
                roads.append((node(i, j), node(i + 1, j)))
                lanes.append(2 if j == arterial_row else 1)
            if j + 1 < ny:
                roads.append((node(i, j), node(i, j + 1)))
                lanes.append(2 if i == arterial_col else 1)
    roads, lanes = np.array(roads), np.array(lanes)
    interior = (ii > 0) & (ii < nx - 1) & (jj > 0) & (jj < ny - 1)
    ring_candidates = np.flatnonzero((interior & (ii != arterial_col) & (jj != arterial_row)).ravel())
    ring_node = int(rng.choice(ring_candidates))
    # Remove a few local roads between 4-way interior junctions (each becomes 3-way; none becomes a bend).
    keep = np.ones(len(roads), bool)
    for _ in range(_NUM_REMOVED_ROADS):
        degree = np.bincount(roads[keep].ravel(), minlength=len(node_xy))
        removable = (
            keep
            & (lanes == 1)
            & (degree[roads[:, 0]] == 4)
            & (degree[roads[:, 1]] == 4)
            & (roads[:, 0] != ring_node)
            & (roads[:, 1] != ring_node)
        )
        keep[rng.choice(np.flatnonzero(removable))] = False
    return node_xy, roads[keep], lanes[keep], ring_node, interior.ravel()


# ----------------------------------------------------------------------------- lanes


class _Lanes:
    """Growing list of lanes while building: dense polylines plus metadata."""

    def __init__(self):
        self.pts, self.kind, self.speed, self.node, self.priority, self.succ = [], [], [], [], [], []
        self.at_mouth, self.stop_line = set(), set()  # road lanes ending at a junction / at a painted line

    def add(self, pts, kind, speed, node=-1, priority=PRIORITY_NORMAL):
        self.pts.append(pts)
        self.kind.append(kind)
        self.speed.append(speed)
        self.node.append(node)
        self.priority.append(priority)
        self.succ.append([])
        return len(self.pts) - 1

    def end_heading(self, lane):
        return _unit(self.pts[lane][-1] - self.pts[lane][-2])

    def start_heading(self, lane):
        return _unit(self.pts[lane][1] - self.pts[lane][0])


def _turn_speed(pts, road_speed):
    """Speed limit of a junction lane: its road's, or lower so lateral acceleration stays comfortable."""
    peak_curv = np.abs(_yaw_and_curvature(pts)[1]).max()
    return float(min(road_speed, np.sqrt(TURN_LAT_ACCEL_MPS2 / max(peak_curv, 1e-6))))


def _build_lanes(node_xy, roads, lanes_per_dir, node_kind, major_roads, mouth_m):
    """All lanes for junction mouths at ``mouth_m`` [NN] metres from each node centre.

    ``major_roads`` maps each priority junction to its two through roads. Returns (lanes, in_lanes) where
    in_lanes maps node -> list of (road, [lane ids entering the node]).
    """
    L = _Lanes()
    road_speed = np.where(lanes_per_dir == 2, ARTERIAL_SPEED_MPS, LOCAL_SPEED_MPS)
    into, out_of = {}, {}  # (road, node) -> lane ids by lane number, heading into / away from node
    for r, (u, v) in enumerate(roads):
        for a, b in ((u, v), (v, u)):
            heading = _unit(node_xy[b] - node_xy[a])
            ids = []
            for k in range(lanes_per_dir[r]):
                offset = (k + 0.5) * LANE_WIDTH_M * _right_of(heading)
                start = node_xy[a] + mouth_m[a] * heading + offset
                end = node_xy[b] - mouth_m[b] * heading + offset
                ids.append(L.add(_resample(np.stack([start, end]), _DENSE_DS_M), LANE_ROAD, road_speed[r]))
            out_of[(r, a)], into[(r, b)] = ids, ids
    in_lanes = {}
    for n in range(len(node_xy)):
        incident = [r for r in range(len(roads)) if n in roads[r]]
        in_lanes[n] = [(r, into[(r, n)]) for r in incident]
        if node_kind[n] != NODE_BEND:
            L.at_mouth.update(lane for r in incident for lane in into[(r, n)])
        if node_kind[n] == NODE_ROUNDABOUT:
            _build_roundabout(L, n, node_xy, roads, incident, into, out_of, mouth_m[n])
            continue
        for r_in in incident:
            minor = node_kind[n] == NODE_PRIORITY and r_in not in major_roads[n]
            if node_kind[n] == NODE_SIGNAL or minor:
                L.stop_line.update(into[(r_in, n)])
            away_in = _unit(node_xy[roads[r_in].sum() - n] - node_xy[n])  # from the node along r_in
            for r_out in incident:
                if r_out == r_in:
                    continue
                away_out = _unit(node_xy[roads[r_out].sum() - n] - node_xy[n])
                turn = wrap_angle(_angle(away_out) - _angle(-away_in))  # > 0 turning left
                n_in, n_out = lanes_per_dir[r_in], lanes_per_dir[r_out]
                if len(incident) == 2 or abs(turn) < np.pi / 4:  # straight on (or the only way, at a bend)
                    pairs = [(k, min(k, n_out - 1)) for k in range(n_in)]
                elif turn > 0:  # left turn: inner lane to inner lane
                    pairs = [(0, 0)]
                else:  # right turn: kerb lane to kerb lane
                    pairs = [(n_in - 1, n_out - 1)]
                curve = _bezier if len(incident) > 2 and abs(turn) < np.pi / 4 else _fillet
                if node_kind[n] != NODE_PRIORITY:
                    priority = PRIORITY_NORMAL
                elif minor:
                    priority = PRIORITY_YIELD
                else:  # along the major road; its left turns cross the oncoming major traffic
                    priority = PRIORITY_NORMAL if turn > np.pi / 4 else PRIORITY_MAJOR
                for k_in, k_out in pairs:
                    lane_in, lane_out = into[(r_in, n)][k_in], out_of[(r_out, n)][k_out]
                    pts = curve(
                        L.pts[lane_in][-1], L.end_heading(lane_in), L.pts[lane_out][0], L.start_heading(lane_out)
                    )
                    c = L.add(
                        pts, LANE_CONNECTOR, _turn_speed(pts, min(road_speed[r_in], road_speed[r_out])), n, priority
                    )
                    L.succ[lane_in].append(c)
                    L.succ[c].append(lane_out)
    return L, in_lanes


def _ring_entry_local(mouth_m):
    """The entry turn in an approach's frame (x out along the road, y to its left, ring centre at 0).

    The entering lane runs along y = +LANE_WIDTH_M / 2 towards the ring, then turns right on a circle of
    radius RING_TURN_RADIUS_M tangent to both the lane and the ring (outside it). Returns the dense curve
    [M, 2] from the mouth (x = mouth_m) to the ring, and the ring angle where it joins.
    """
    lane_y, rho = 0.5 * LANE_WIDTH_M, RING_TURN_RADIUS_M
    centre = np.array([np.sqrt((RING_RADIUS_M + rho) ** 2 - (lane_y + rho) ** 2), lane_y + rho])
    a_end = _angle(-centre)  # the ring touches the turn circle on the line between the two centres
    angles = np.linspace(-np.pi / 2, a_end, max(int(np.ceil(rho * (a_end + np.pi / 2) / -_DENSE_DS_M)), 2))
    arc = centre + rho * np.stack([np.cos(angles), np.sin(angles)], -1)
    pts = _resample(np.concatenate([[[mouth_m, lane_y]], arc]), _DENSE_DS_M)
    return pts, _angle(arc[-1])


def _ring_mouth_m():
    """Distance from the roundabout's centre to its approach mouths: the entry turn plus 3 m of straight."""
    lane_y, rho = 0.5 * LANE_WIDTH_M, RING_TURN_RADIUS_M
    return np.sqrt((RING_RADIUS_M + rho) ** 2 - (lane_y + rho) ** 2) + 3.0


def _build_roundabout(L, n, node_xy, roads, incident, into, out_of, mouth):
    """Ring arcs, entries and exits of the roundabout at node ``n`` (one-lane roads only).

    An exit is the mirror image of an entry (y -> -y), driven the other way.
    """
    centre = node_xy[n]
    ring_speed = float(np.sqrt(TURN_LAT_ACCEL_MPS2 * RING_RADIUS_M))
    entry_local, port = _ring_entry_local(mouth)
    exit_local = entry_local[::-1] * np.array([1.0, -1.0])
    turn_speed = _turn_speed(entry_local, ring_speed)
    axis = {r: _angle(node_xy[roads[r].sum() - n] - centre) for r in incident}
    ports = sorted([(axis[r] - port, "exit", r) for r in incident] + [(axis[r] + port, "entry", r) for r in incident])
    arcs = []  # arcs[i] runs counter-clockwise from ports[i] to ports[i + 1]
    for i, (a0, _, _) in enumerate(ports):
        a1 = ports[(i + 1) % len(ports)][0]
        arcs.append(
            L.add(
                _arc(centre, RING_RADIUS_M, a0, a1 + 2 * np.pi * (a1 <= a0)), LANE_RING, ring_speed, n, PRIORITY_MAJOR
            )
        )
    for i, (_, kind, r) in enumerate(ports):
        arriving, leaving = arcs[i - 1], arcs[i]
        L.succ[arriving].append(leaving)
        x_axis = np.array([np.cos(axis[r]), np.sin(axis[r])])
        to_town = lambda local: centre + local[:, :1] * x_axis + local[:, 1:] * np.array([-x_axis[1], x_axis[0]])
        if kind == "entry":
            lane_in = into[(r, n)][0]
            L.stop_line.add(lane_in)
            entry = L.add(to_town(entry_local), LANE_RING_ENTRY, turn_speed, n, PRIORITY_YIELD)
            L.succ[lane_in].append(entry)
            L.succ[entry].append(leaving)
        else:
            exit_ = L.add(to_town(exit_local), LANE_RING_EXIT, turn_speed, n, PRIORITY_MAJOR)
            L.succ[arriving].append(exit_)
            L.succ[exit_].append(out_of[(r, n)][0])


def _junction_kinds(rng, node_xy, roads, lanes_per_dir, ring_node, interior):
    """NODE_* of every node, and the two through roads of each priority junction."""
    degree = np.bincount(roads.ravel(), minlength=len(node_xy))
    kind = np.full(len(node_xy), NODE_BEND)
    major_roads = {}
    for n in np.flatnonzero(degree >= 3):
        incident = np.flatnonzero((roads == n).any(1))
        if n == ring_node:
            kind[n] = NODE_ROUNDABOUT
        elif (lanes_per_dir[incident] == 2).any() or (interior[n] and rng.uniform() < SIGNAL_SHARE):
            kind[n] = NODE_SIGNAL
        else:
            kind[n] = NODE_PRIORITY
            # The through road: the straightest pair of roads (at a 4-way either pair, at random).
            away = {r: _angle(node_xy[roads[r].sum() - n] - node_xy[n]) for r in incident}
            pairs = [(a, b) for i, a in enumerate(incident) for b in incident[i + 1 :]]
            bend = [abs(np.pi - abs(wrap_angle(away[a] - away[b]))) + rng.uniform(0.0, 0.5) for a, b in pairs]
            major_roads[n] = set(pairs[int(np.argmin(bend))])
    return kind, major_roads


def _lanes_with_feasible_turns(node_xy, roads, lanes_per_dir, node_kind, major_roads):
    """Grows each junction's mouth distance until all its lanes turn no tighter than MIN_TURN_RADIUS_M."""
    kerb_offset = (lanes_per_dir - 0.5) * LANE_WIDTH_M
    mouth_m = np.zeros(len(node_xy))
    for n in range(len(node_xy)):
        incident = (roads == n).any(1)
        mouth_m[n] = kerb_offset[incident].max() + MIN_TURN_RADIUS_M + 1.0
    mouth_m[node_kind == NODE_ROUNDABOUT] = _ring_mouth_m()
    for _ in range(20):
        L, in_lanes = _build_lanes(node_xy, roads, lanes_per_dir, node_kind, major_roads, mouth_m)
        too_tight = np.zeros(len(node_xy), bool)
        for pts, node in zip(L.pts, L.node):
            if node >= 0 and np.abs(_yaw_and_curvature(pts)[1]).max() > 1.0 / MIN_TURN_RADIUS_M:
                too_tight[node] = True
        if not too_tight.any():
            return L, in_lanes, mouth_m
        mouth_m[too_tight] += 1.0
    raise RuntimeError("could not fit junction turns within the minimum turn radius")


def _strongly_connected(succ):
    """Whether the directed graph with adjacency lists ``succ`` is strongly connected."""
    pred = [[] for _ in succ]
    for a, bs in enumerate(succ):
        for b in bs:
            pred[b].append(a)

    def reaches_all(adj):
        seen, todo = {0}, [0]
        while todo:
            for b in adj[todo.pop()]:
                if b not in seen:
                    seen.add(b)
                    todo.append(b)
        return len(seen) == len(adj)

    return reaches_all(succ) and reaches_all(pred)


# ----------------------------------------------------------------------------- lights and conflicts


def _lights(rng, node_xy, node_kind, roads, lanes_per_dir, in_lanes, L):
    """Split-phase lights: one per (signalised junction, approach). Sets each approach lane's light.

    Returns (lane_light [NL], cycle_s, green_start_s, green_s, light_node, light_xy [NT, 2]).
    """
    lane_light = -np.ones(len(L.pts), np.int64)
    cycle, start, green, light_node, light_xy = [], [], [], [], []
    for n in np.flatnonzero(node_kind == NODE_SIGNAL):
        approaches = sorted(in_lanes[n], key=lambda rl: _angle(node_xy[roads[rl[0]].sum() - n] - node_xy[n]))
        greens = [GREEN_ARTERIAL_S if lanes_per_dir[r] == 2 else GREEN_LOCAL_S for r, _ in approaches]
        junction_cycle = sum(g + YELLOW_S + ALL_RED_S for g in greens)
        t = rng.uniform(0.0, junction_cycle)  # junctions are not synchronised
        for (r, ids), g in zip(approaches, greens):
            lane_light[ids] = len(cycle)
            cycle.append(junction_cycle)
            start.append(t % junction_cycle)
            green.append(g)
            light_node.append(n)
            light_xy.append(np.mean([L.pts[i][-1] for i in ids], axis=0))
            t += g + YELLOW_S + ALL_RED_S
    return lane_light, np.array(cycle), np.array(start), np.array(green), np.array(light_node), np.array(light_xy)


def _conflicts(L, length):
    """Pairwise conflict intervals of lanes whose centre lines pass within CONFLICT_DIST_M (``length``: each
    lane's length m, :func:`_lane_lengths`).

    Returns a list per lane of (other lane, in_m, out_m, by_priority).
    """
    n = len(L.pts)
    succ2 = [set(L.succ[a]) | {c for b in L.succ[a] for c in L.succ[b]} for a in range(n)]
    pred = [set() for _ in range(n)]
    for a in range(n):
        for b in L.succ[a]:
            pred[b].add(a)
    lo = np.array([p.min(0) for p in L.pts]) - CONFLICT_DIST_M
    hi = np.array([p.max(0) for p in L.pts]) + CONFLICT_DIST_M
    near = np.all((lo[:, None] <= hi[None]) & (lo[None] <= hi[:, None]), axis=-1)
    table = [[] for _ in range(n)]
    for a, b in zip(*np.nonzero(np.triu(near, 1))):
        if b in succ2[a] or a in succ2[b]:  # following along one path is the car-following model's job
            continue
        # Distances only between the points inside the other lane's box grown by CONFLICT_DIST_M: no point
        # outside it is that close to the other lane.
        ia = np.flatnonzero(np.all((L.pts[a] >= lo[b]) & (L.pts[a] <= hi[b]), axis=-1))
        ib = np.flatnonzero(np.all((L.pts[b] >= lo[a]) & (L.pts[b] <= hi[a]), axis=-1))
        close = np.zeros((len(L.pts[a]), len(L.pts[b])), bool)
        close[np.ix_(ia, ib)] = np.linalg.norm(L.pts[a][ia, None] - L.pts[b][None, ib], axis=-1) < CONFLICT_DIST_M
        if not close.any():
            continue
        by_priority = not (pred[a] & pred[b])
        for x, y, rows in ((a, b, close.any(1)), (b, a, close.any(0))):
            idx = np.flatnonzero(rows)
            s_in = max((idx[0] - 1) * _DENSE_DS_M, 0.0)
            s_out = min((idx[-1] + 1) * _DENSE_DS_M, length[x])
            table[x].append((y, s_in, s_out, by_priority))
    return table


# ----------------------------------------------------------------------------- raster


class _Raster:
    """Town-frame drawing onto a cell grid with cv2 (sub-pixel coordinates, 4 fractional bits)."""

    SHIFT = 4

    def __init__(self, origin, shape):
        self.origin, self.shape = origin, shape

    def px(self, xy):
        return np.round(((np.asarray(xy) - self.origin) / MAP_RES_M - 0.5) * (1 << self.SHIFT)).astype(np.int32)

    def cell(self, xy):
        """(col, row) of the cell containing town point(s) ``xy``."""
        return np.floor((np.asarray(xy) - self.origin) / MAP_RES_M).astype(int)

    def poly(self, img, xy, value):
        cv2.fillPoly(img, [self.px(xy)], value, cv2.LINE_8, self.SHIFT)

    def line(self, img, xy, value, width_m):
        thickness = max(int(round(width_m / MAP_RES_M)), 1)
        cv2.polylines(img, [self.px(xy)], False, value, thickness, cv2.LINE_8, self.SHIFT)

    def disk(self, img, centre, radius_m, value):
        cv2.circle(
            img,
            tuple(self.px(centre)),
            int(round(radius_m / MAP_RES_M * (1 << self.SHIFT))),
            value,
            -1,
            cv2.LINE_8,
            self.SHIFT,
        )


def _disk_kernel(radius_m):
    r = int(np.ceil(radius_m / MAP_RES_M))
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _rasterise(node_xy, node_kind, roads, lanes_per_dir, mouth_m, L):
    """Semantic map and its origin, plus the stop lines (ends [NS, 2, 2], lane [NS])."""
    lo = node_xy.min(0) - BUILDING_BELT_M - MAP_MARGIN_M
    hi = node_xy.max(0) + BUILDING_BELT_M + MAP_MARGIN_M
    shape = tuple(np.ceil((hi - lo) / MAP_RES_M).astype(int)[::-1])  # (rows = y, cols = x)
    raster = _Raster(lo, shape)
    road = np.zeros(shape, np.uint8)
    ring = np.flatnonzero(node_kind == NODE_ROUNDABOUT)
    for r, (u, v) in enumerate(roads):
        heading = _unit(node_xy[v] - node_xy[u])
        half = lanes_per_dir[r] * LANE_WIDTH_M * _right_of(heading)
        a = node_xy[u] + heading * (mouth_m[u] if u in ring else 0.0)
        b = node_xy[v] - heading * (mouth_m[v] if v in ring else 0.0)
        raster.poly(road, [a + half, b + half, b - half, a - half], 1)
    for n in range(len(node_xy)):
        if n in ring:
            raster.disk(road, node_xy[n], RING_RADIUS_M + 0.5 * LANE_WIDTH_M + 0.5, 1)
            raster.disk(road, node_xy[n], RING_RADIUS_M - 0.5 * LANE_WIDTH_M - 0.5, 0)
            continue
        mouths = []
        for r in np.flatnonzero((roads == n).any(1)):
            away = _unit(node_xy[roads[r].sum() - n] - node_xy[n])
            half = lanes_per_dir[r] * LANE_WIDTH_M * _right_of(away)
            mouths += [node_xy[n] + mouth_m[n] * away + half, node_xy[n] + mouth_m[n] * away - half]
        raster.poly(road, cv2.convexHull(np.array(mouths, np.float32))[:, 0], 1)
    for pts, kind in zip(L.pts, L.kind):
        if kind != LANE_ROAD:  # junction lanes get a strip wider than a lane, so bodies on curves stay on road
            raster.line(road, pts, 1, LANE_WIDTH_M + 1.0)
    sem = np.where(cv2.dilate(road, _disk_kernel(SIDEWALK_WIDTH_M)) > 0, SEM_SIDEWALK, SEM_OFFROAD).astype(np.uint8)
    sem[road > 0] = SEM_ROAD
    for r, (u, v) in enumerate(roads):
        heading = _unit(node_xy[v] - node_xy[u])
        a, b = node_xy[u] + heading * mouth_m[u], node_xy[v] - heading * mouth_m[v]
        raster.line(sem, [a, b], SEM_CENTRE_YELLOW, 0.3)
        if lanes_per_dir[r] == 2:  # dashes 3 m on, 3 m off between same-direction lanes
            length = np.linalg.norm(b - a)
            for side in (1.0, -1.0):
                offset = side * LANE_WIDTH_M * _right_of(heading)
                for t in np.arange(1.5, length - 3.0, 6.0):
                    raster.line(sem, [a + offset + t * heading, a + offset + (t + 3.0) * heading], SEM_LANE_WHITE, 0.2)
    stop_ends, stop_lane = [], []
    for lane in sorted(L.stop_line):
        end, heading = L.pts[lane][-1], L.end_heading(lane)
        across = 0.5 * LANE_WIDTH_M * _right_of(heading)
        stop_ends.append([end - across, end + across])  # the line not to cross: the lane's end
        stop_lane.append(lane)
        # The painted bar: STOP_BAR_M deep, just before the line; a vehicle that stops comes to rest with its
        # front at the bar's near edge (world.STOP_SHORT_M).
        back = STOP_BAR_M * heading
        raster.poly(sem, [end - across, end + across, end + across - back, end - across - back], SEM_STOP_LINE)
    return sem, lo, np.array(stop_ends), np.array(stop_lane)


# ----------------------------------------------------------------------------- buildings

_FACADES = np.array(
    [
        [196, 180, 150],
        [170, 90, 70],
        [150, 150, 155],
        [220, 215, 200],
        [120, 100, 85],
        [205, 170, 110],
        [90, 110, 140],
        [180, 120, 100],
        [230, 225, 215],
        [110, 120, 110],
    ]
)
_GLASS = np.array([[70, 110, 150], [90, 140, 170], [60, 70, 85], [140, 160, 175], [40, 90, 110]])
_BRIGHT = np.array([[220, 50, 40], [240, 190, 30], [40, 150, 70], [240, 120, 30], [50, 90, 200]])
_TREES = np.array([[40, 110, 40], [60, 130, 50], [30, 90, 45], [80, 120, 40]])
_POLES = np.array([[90, 90, 95], [60, 60, 65], [150, 150, 150]])

# kind: (how many, where ("block" or "verge"), length range m, width range m, height range m, palette)
_LANDMARKS = (
    (TOWER, 7, "block", (10.0, 16.0), (10.0, 16.0), (35.0, 60.0), _GLASS),
    (BUILDING, 150, "block", (9.0, 30.0), (8.0, 18.0), (6.0, 30.0), _FACADES),
    (KIOSK, 20, "verge", (2.5, 4.0), (2.0, 3.0), (3.0, 3.6), _BRIGHT),
    (TREE, 130, "verge", (0.8, 1.3), (0.8, 1.3), (5.0, 11.0), _TREES),
    (POLE, 40, "verge", (0.35, 0.45), (0.35, 0.45), (6.0, 9.0), _POLES),
)


def _buildings(rng, sem, raster, node_xy, roads, ring_xy):
    """Rejection-samples landmark boxes on offroad cells; returns (box [NB, 5], height, color, kind)."""
    paved = (sem != SEM_OFFROAD).astype(np.uint8)
    free = cv2.dilate(paved, _disk_kernel(BUILDING_CLEARANCE_M)) == 0
    (c_lo, r_lo), (c_hi, r_hi) = (
        raster.cell(node_xy.min(0) - BUILDING_BELT_M),
        raster.cell(node_xy.max(0) + BUILDING_BELT_M),
    )
    in_belt = np.zeros_like(free)
    in_belt[r_lo : r_hi + 1, c_lo : c_hi + 1] = True
    free &= in_belt
    verge = free & (cv2.dilate(paved, _disk_kernel(BUILDING_CLEARANCE_M + 2.5)) > 0)
    road_a, road_b = node_xy[roads[:, 0]], node_xy[roads[:, 1]]
    boxes, heights, colors, kinds = [], [], [], []

    def place(centre, yaw, length, width, height, color, kind, gap_m):
        c, s = np.cos(yaw), np.sin(yaw)
        half = np.array([[length, width], [length, -width], [-length, -width], [-length, width]]) / 2
        # Not geometry.box_corners: BLAS rounds this product differently (fused multiply-adds) in the last
        # bit, and every town's footprints, hence its buildings, are pinned to this rounding.
        corners = centre + half @ np.array([[c, s], [-s, c]])
        pad = int(np.ceil(gap_m / MAP_RES_M)) + 1
        (c0, r0), (c1, r1) = raster.cell(corners.min(0)) - pad, raster.cell(corners.max(0)) + pad
        if r0 < 0 or c0 < 0 or r1 >= sem.shape[0] or c1 >= sem.shape[1]:
            return False
        footprint = np.zeros((r1 - r0 + 1, c1 - c0 + 1), np.uint8)
        raster.poly(footprint, corners - np.array([c0, r0]) * MAP_RES_M, 1)
        window = free[r0 : r1 + 1, c0 : c1 + 1]  # a view: clearing it clears ``free``
        if not window[footprint > 0].all():
            return False
        # Keep a gap to the next landmark: the footprint grown by gap_m is no longer free.
        window[cv2.dilate(footprint, _disk_kernel(gap_m)) > 0] = False
        boxes.append([*centre, yaw, length, width])
        heights.append(height)
        colors.append(np.clip(color + rng.integers(-15, 16, 3), 0, 255))
        kinds.append(kind)
        return True

    place(ring_xy, 0.0, 3.0, 3.0, 14.0, np.array([200, 160, 60]), MONUMENT, 1.0)
    for kind, count, where, length_m, width_m, height_m, palette in _LANDMARKS:
        pool = np.argwhere(free if where == "block" else verge)
        placed = 0
        for _ in range(40 * count):
            if placed == count:
                break
            r, c = pool[rng.integers(len(pool))]
            centre = raster.origin + (np.array([c, r]) + 0.5) * MAP_RES_M
            # Align with the nearest road, so blocks look like streets.
            t = np.clip(
                np.einsum("rd,rd->r", centre - road_a, road_b - road_a)
                / np.einsum("rd,rd->r", road_b - road_a, road_b - road_a),
                0,
                1,
            )
            nearest = np.argmin(np.linalg.norm(road_a + t[:, None] * (road_b - road_a) - centre, axis=1))
            yaw = _angle(road_b[nearest] - road_a[nearest])
            length, width = rng.uniform(*length_m), rng.uniform(*width_m)
            height = height_m[0] + (height_m[1] - height_m[0]) * rng.uniform() ** 1.5
            placed += place(
                centre,
                yaw,
                length,
                width,
                height,
                palette[rng.integers(len(palette))],
                kind,
                2.0 if where == "block" else 1.0,
            )
    return np.array(boxes), np.array(heights), np.array(colors), np.array(kinds)


# ----------------------------------------------------------------------------- assembly


def _pad(rows, width, fill):
    out = np.full((len(rows), width), fill, dtype=np.asarray(fill).dtype)
    for i, row in enumerate(rows):
        out[i, : len(row)] = row
    return out


def _sampled(pts, num_samples):
    """Stored lane samples: xy [P, 2], yaw [P], curvature [P] every LANE_DS_M, straight on past the end."""
    yaw, curv = _yaw_and_curvature(pts)
    s_dense = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    s = np.arange(num_samples) * LANE_DS_M
    inside = np.minimum(s, s_dense[-1])
    end_heading = _unit(pts[-1] - pts[-2])
    xy = np.stack([np.interp(inside, s_dense, pts[:, 0]), np.interp(inside, s_dense, pts[:, 1])], -1)
    xy += (s - inside)[:, None] * end_heading
    curv = np.where(s > s_dense[-1], 0.0, np.interp(inside, s_dense, curv))
    return xy, wrap_angle(np.interp(inside, s_dense, yaw)), curv


@functools.lru_cache(maxsize=8)
def _lane_graph(seed):
    """The road network, its junctions and the lanes through them (the first draws from the town's
    generator), and that generator's state after them, from which the build draws the rest. Once per seed:
    a launcher's checks (:func:`spawn_slots`) and the build both read it, and neither changes it."""
    rng = np.random.default_rng(seed)
    node_xy, roads, lanes_per_dir, ring_node, interior = _road_network(rng)
    node_kind, major_roads = _junction_kinds(rng, node_xy, roads, lanes_per_dir, ring_node, interior)
    L, in_lanes, mouth_m = _lanes_with_feasible_turns(node_xy, roads, lanes_per_dir, node_kind, major_roads)
    return (node_xy, roads, lanes_per_dir, ring_node, node_kind, L, in_lanes, mouth_m), rng.bit_generator.state


def _lane_lengths(L):
    return np.array([np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in L.pts])


def _spawn_slots(L, length):
    """(lane, arc position m) of every reset slot: along road lanes, SPAWN_SPACING_M apart."""
    return [
        (lane, s)
        for lane in np.flatnonzero(np.array(L.kind) == LANE_ROAD)
        for s in np.arange(4.0, length[lane] - 8.0, SPAWN_SPACING_M)
    ]


def _build_town_np(seed):
    graph, after_graph = _lane_graph(seed)
    node_xy, roads, lanes_per_dir, ring_node, node_kind, L, in_lanes, mouth_m = graph
    rng = np.random.default_rng(seed)
    rng.bit_generator.state = after_graph
    node_degree = np.bincount(roads.ravel(), minlength=len(node_xy))
    if not _strongly_connected(L.succ):
        raise RuntimeError(f"town {seed}: lane graph is not strongly connected")
    lane_light, *lights = _lights(rng, node_xy, node_kind, roads, lanes_per_dir, in_lanes, L)
    sem, origin, stop_line, stop_lane = _rasterise(node_xy, node_kind, roads, lanes_per_dir, mouth_m, L)
    buildings = _buildings(rng, sem, _Raster(origin, sem.shape), node_xy, roads, node_xy[ring_node])

    length = _lane_lengths(L)
    if length.min() < 2.0 or length.max() > MAX_LANE_LENGTH_M:  # a step crosses at most one lane boundary
        raise RuntimeError(f"town {seed}: lane lengths {length.min():.2f}..{length.max():.2f} m out of range")
    num_samples = int(np.ceil(length.max() / LANE_DS_M)) + 2
    xy, yaw, curv = map(np.stack, zip(*(_sampled(p, num_samples) for p in L.pts)))
    table = _conflicts(L, length)
    width = max(len(row) for row in table)
    conf_lane = _pad([[c[0] for c in row] for row in table], width, np.int32(-1))
    mirror = [[[c[0] for c in table[b]].index(a) for b, *_ in row] for a, row in enumerate(table)]
    kind = np.array(L.kind)
    spawn = _spawn_slots(L, length)
    f32, i32 = np.float32, np.int32
    box, height, color, building_kind = buildings
    cycle, green_start, green, light_node, light_xy = lights
    return Town(
        sem_map=sem,
        map_origin_m=origin.astype(f32),
        map_res_m=np.array(MAP_RES_M, f32),
        building_box=box.astype(f32),
        building_height_m=height.astype(f32),
        building_color=color.astype(np.uint8),
        building_kind=building_kind.astype(i32),
        lane_xy_m=xy.astype(f32),
        lane_yaw_rad=yaw.astype(f32),
        lane_curv_1pm=curv.astype(f32),
        lane_length_m=length.astype(f32),
        lane_succ=_pad(L.succ, max(map(len, L.succ)), i32(-1)),
        lane_num_succ=np.array([len(s) for s in L.succ], i32),
        lane_speed_limit_mps=np.array(L.speed, f32),
        lane_kind=kind.astype(i32),
        lane_priority=np.array(L.priority, i32),
        lane_light=lane_light.astype(i32),
        lane_at_mouth=np.isin(np.arange(len(kind)), sorted(L.at_mouth)),
        conf_lane=conf_lane,
        conf_mirror=_pad(mirror, width, i32(0)),
        conf_in_m=_pad([[c[1] for c in row] for row in table], width, f32(0)),
        conf_out_m=_pad([[c[2] for c in row] for row in table], width, f32(0)),
        conf_by_priority=_pad([[c[3] for c in row] for row in table], width, False),
        light_cycle_s=cycle.astype(f32),
        light_green_start_s=green_start.astype(f32),
        light_green_s=green.astype(f32),
        light_node=light_node.astype(i32),
        light_xy_m=light_xy.astype(f32),
        stop_line_m=stop_line.astype(f32),
        stop_line_lane=stop_lane.astype(i32),
        stop_line_light=lane_light[stop_lane].astype(i32),
        road_xy_m=node_xy[roads].astype(f32),
        road_lanes_per_dir=lanes_per_dir.astype(i32),
        node_xy_m=node_xy.astype(f32),
        node_kind=node_kind.astype(i32),
        node_degree=node_degree.astype(i32),
        ring_radius_m=np.array(RING_RADIUS_M, f32),
        spawn_lane=np.array([lane for lane, _ in spawn], i32),
        spawn_s_m=np.array([s for _, s in spawn], f32),
    )
