"""A hand-built drive in a built town: a vehicle that passes behind a building, which the world's traffic
never makes.

A town's buildings stand on offroad cells, at least ``BUILDING_CLEARANCE_M`` beyond the sidewalk, so at least
8 m from a one-lane street's centre line, and the bird-eye view reaches ``BEV_AHEAD_M`` ahead and
``BEV_SIDE_M`` aside: no building of the training town hides a vehicle inside the view (BUILD_NOTES,
Evaluation, counts both the world's drives and hand-built scenes). :func:`kerb_building_drive` builds one: the
ego stands on a lane before a signalised four-way junction, one building is added on the junction's near
right corner, its inner corner at the kerb and standing on the sidewalk (a building at the street line, as
many real streets have them), and one vehicle drives at a constant speed straight across the junction from the ego's left and away
down the street to its right, behind that building. Every other vehicle is out of every sensor's reach.

NumPy on the host, but for the lines of sight to each candidate path (one compiled program: op by op, a path
of each length compiled its own hundreds of small ones) and the sensors
(:func:`e2e_percep_jax.sim.sensors.observe`) that the caller runs on the returned states.
"""

import itertools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import sensors
from e2e_percep_jax.sim import town as town_lib
from e2e_percep_jax.sim.motion import DT_S
from e2e_percep_jax.sim.world import EGO, WorldState

BUILDING_SIDE_M = 12.0  # the added building's footprint, square
BUILDING_HEIGHT_M = 10.0  # above the lidar's highest beam where it meets the building
BUILDING_COLOR = (150, 120, 100)
APPROACH_M = 30.0  # the vehicle's path along the lane before the junction's connector, and after it
SEEN_FRAMES = 10  # frames the vehicle must be in plain sight before the building hides it


class KerbBuildingDrive(NamedTuple):
    """town: the town with the added building (its last ``building_box`` row); states: list of WorldState, one
    a frame, the ego standing (row ``EGO``) and the driven vehicle in row 1 (slot 0 of the frame contract's
    boxes); node: the junction's index; hidden_frames: the frames in which, in plan view, the vehicle lies in
    the bird-eye view with both sensors' lines of sight to its centre crossing the added building."""

    town: town_lib.Town
    states: list
    node: int
    hidden_frames: np.ndarray


def _path(town_np: dict, lanes, step_m: float):
    """(x, y, yaw) [F, 3] of a vehicle centre driving along ``lanes`` (lane, from_m, to_m), ``step_m`` a
    frame."""
    xy, yaw = [], []
    for lane, from_m, to_m in lanes:
        idx = np.arange(int(max(0.0, from_m)), int(min(town_np["lane_length_m"][lane], to_m)))
        xy.append(town_np["lane_xy_m"][lane, idx])
        yaw.append(town_np["lane_yaw_rad"][lane, idx])
    xy, yaw = np.concatenate(xy).astype(np.float64), np.unwrap(np.concatenate(yaw).astype(np.float64))
    arc_m = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    s = np.arange(0.0, arc_m[-1], step_m)
    return np.stack([np.interp(s, arc_m, xy[:, 0]), np.interp(s, arc_m, xy[:, 1]), np.interp(s, arc_m, yaw)], -1)


def _corner_building(town: town_lib.Town, node_xy, ego_yaw: float):
    """The building box [5] (town frame) on the near right corner of the junction at ``node_xy`` as the ego
    approaches it heading ``ego_yaw``: its inner corner at the kerb, the first point off the road from the
    junction's centre along the corner's diagonal, its sides along the ego's axes, standing on the sidewalk and
    the offroad behind it; None if its footprint covers road."""
    forward, left = np.array([np.cos(ego_yaw), np.sin(ego_yaw)]), np.array([-np.sin(ego_yaw), np.cos(ego_yaw)])
    diagonal = -(forward + left) / np.sqrt(2.0)  # back towards the ego, and to its right
    sem = lambda xy: np.asarray(sensors.sem_classes_at(town, xy[..., 0], xy[..., 1])[0])
    steps_m = np.arange(0.0, 20.0, 0.25)
    off_road = sem(node_xy + steps_m[:, None] * diagonal) != town_lib.SEM_ROAD
    if not off_road.any():
        return None
    corner = node_xy + steps_m[np.argmax(off_road)] * diagonal
    centre = corner + BUILDING_SIDE_M / 2 * diagonal * np.sqrt(2.0)
    u = np.linspace(-0.5, 0.5, 9) * BUILDING_SIDE_M
    footprint = centre + u[:, None, None] * forward + u[None, :, None] * left
    if np.any(np.isin(sem(footprint), [town_lib.SEM_ROAD, *range(town_lib.SEM_LANE_WHITE, town_lib.NUM_SEM_CLASSES)])):
        return None
    return np.array([*centre, ego_yaw, BUILDING_SIDE_M, BUILDING_SIDE_M])


PAD_FRAMES = 64  # paths padded to a multiple of this: one compiled sight test serves paths of many lengths


@jax.jit
def _sight_padded(ego_xy, ego_yaw, boxes_xyyaw, building):
    rel = geo.town_to_ego(boxes_xyyaw[:, :2], ego_xy, ego_yaw)
    b = geo.box_to_ego(building, ego_xy, ego_yaw)
    crossed = [sensors.ray_box_slab(x0, 0.0, rel[:, 0] - x0, rel[:, 1], b)[0] < 1.0 for x0 in (0.0, sensors.CAMERA_X_M)]
    in_view = geo.in_bev_view(rel)
    return in_view & crossed[0] & crossed[1], in_view


def _sight(ego_xy, ego_yaw, boxes_xyyaw, building):
    """(hidden, in_view), bool [F] each: the vehicle's centre in the bird-eye view, and that with the lines of
    sight from both the lidar (the ego's centre) and the camera (``CAMERA_X_M`` ahead) crossing ``building``
    [5] (town frame)."""
    frames = len(boxes_xyyaw)
    padded = np.pad(boxes_xyyaw, ((0, -frames % PAD_FRAMES), (0, 0)), mode="edge")
    hidden, in_view = _sight_padded(ego_xy, ego_yaw, padded, building)
    return np.asarray(hidden)[:frames], np.asarray(in_view)[:frames]


def _stretch_after_sight(hidden, in_view):
    """The longest run of ``hidden`` frames right after SEEN_FRAMES frames in view and not hidden: (first frame,
    length), (0, 0) if none."""
    best, f = (0, 0), SEEN_FRAMES
    while f < len(hidden):
        if hidden[f] and np.all(in_view[f - SEEN_FRAMES : f] & ~hidden[f - SEEN_FRAMES : f]):
            g = f
            while g < len(hidden) and hidden[g]:
                g += 1
            best, f = max(best, (f, g - f), key=lambda r: r[1]), g
        else:
            f += 1
    return best


def kerb_building_drive(
    town: town_lib.Town, state: WorldState, speed_mps: float = 2.0, ahead_m: tuple = (17.0, 18.0, 19.0, 20.0, 21.0)
):
    """:class:`KerbBuildingDrive` in ``town``, its other fields taken from ``state`` (a world's reset):
    of every signalised four-way junction, approach and straight path across it from the ego's left, the one
    whose vehicle the added building hides longest in plan view right after ``SEEN_FRAMES`` frames in sight.
    The ego stands where its lane is one of ``ahead_m`` from the junction's centre; the vehicle drives
    ``speed_mps``. ValueError if no junction of ``town`` gives a hidden stretch."""
    t = {k: np.asarray(v) for k, v in town._asdict().items()}
    best = None
    ends = t["lane_xy_m"][np.arange(len(t["lane_kind"])), np.maximum(t["lane_length_m"].astype(int) - 1, 0)]
    for node in np.nonzero((t["node_kind"] == town_lib.NODE_SIGNAL) & (t["node_degree"] == 4))[0]:
        node_xy = t["node_xy_m"][node].astype(np.float64)
        incoming = np.nonzero(
            (t["lane_kind"] == town_lib.LANE_ROAD) & t["lane_at_mouth"] & (np.hypot(*(ends - node_xy).T) < 20.0)
        )[0]
        for lane, distance_m in itertools.product(incoming, ahead_m):
            length = int(t["lane_length_m"][lane])
            gap = np.abs(np.hypot(*(t["lane_xy_m"][lane, :length] - node_xy).T) - distance_m)
            at = int(np.argmin(gap))
            if gap[at] > 1.0:
                continue
            ego_xy, ego_yaw = t["lane_xy_m"][lane, at].astype(np.float64), float(t["lane_yaw_rad"][lane, at])
            building = _corner_building(town, node_xy, ego_yaw)
            if building is None:
                continue
            rightwards = ego_yaw - np.pi / 2
            for before in incoming:
                if (
                    abs(geo.wrap_angle(t["lane_yaw_rad"][before, int(t["lane_length_m"][before]) - 1] - rightwards))
                    > 0.5
                ):
                    continue
                for connector in t["lane_succ"][before][: t["lane_num_succ"][before]]:
                    after = t["lane_succ"][connector][0]
                    if abs(geo.wrap_angle(t["lane_yaw_rad"][after, 0] - rightwards)) > 0.5:
                        continue  # a turn, not straight across
                    boxes = _path(
                        t,
                        [
                            (before, t["lane_length_m"][before] - APPROACH_M, np.inf),
                            (connector, 0.0, np.inf),
                            (after, 0.0, APPROACH_M),
                        ],
                        speed_mps * DT_S,
                    )
                    hidden, in_view = _sight(ego_xy, ego_yaw, boxes, building)
                    first, length = _stretch_after_sight(hidden, in_view)
                    if length and (best is None or length > best[0]):
                        best = (length, int(node), ego_xy, ego_yaw, building, boxes, np.arange(first, first + length))
    if best is None:
        raise ValueError("no signalised four-way junction of this town gives a vehicle hidden by a kerb building")
    _, node, ego_xy, ego_yaw, building, boxes, hidden_frames = best
    added = lambda field, row: jnp.concatenate(
        [jnp.asarray(getattr(town, field)), jnp.asarray([row], getattr(town, field).dtype)]
    )
    town = town._replace(
        building_box=added("building_box", building),
        building_height_m=added("building_height_m", BUILDING_HEIGHT_M),
        building_color=added("building_color", BUILDING_COLOR),
        building_kind=added("building_kind", town_lib.BUILDING_KIND_NAMES.index("building")),
    )
    out_of_reach = np.asarray(state.veh_box).copy()
    out_of_reach[:, :2] = sensors.OUT_OF_REACH_M
    out_of_reach[EGO, :3] = [*ego_xy, ego_yaw]
    speed = np.zeros(out_of_reach.shape[0], np.float32)
    speed[1] = speed_mps
    states = []
    for box in boxes:
        veh_box = out_of_reach.copy()
        veh_box[1, :3] = box
        states.append(
            state._replace(
                veh_box=jnp.asarray(veh_box, jnp.float32),
                veh_speed_mps=jnp.asarray(speed),
                ego_action=jnp.zeros(2, jnp.float32),
            )
        )
    return KerbBuildingDrive(town, states, node, hidden_frames)


def observe_drive(drive: KerbBuildingDrive, image_size: int) -> list:
    """The frames (dicts of NumPy arrays, :func:`sensors.observe`'s with its lidar scan) of ``drive``."""
    observe = jax.jit(sensors.observe, static_argnums=2)
    return [{k: np.asarray(v) for k, v in observe(s, drive.town, image_size).items()} for s in drive.states]
