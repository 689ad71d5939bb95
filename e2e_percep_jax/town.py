"""The static town: roads, lanes, junctions, lights, sidewalks, buildings and its semantic raster.

Built once per seed with NumPy (:func:`build_town`), then held as a pytree of arrays (:class:`Town`)
that every pure-JAX world and sensor function takes as a constant argument.
"""
from typing import NamedTuple

import numpy as np

# Semantic classes of ``Town.sem_map`` (and of the roadmap image before colouring).
SEM_OFFROAD = 0  # terrain between roads (buildings stand here)
SEM_ROAD = 1  # drivable asphalt, junctions included
SEM_SIDEWALK = 2
SEM_LANE_WHITE = 3  # dashed white divider between same-direction lanes
SEM_CENTRE_YELLOW = 4  # solid yellow line between opposite directions
SEM_STOP_LINE = 5  # white bar where a lane meets a junction
NUM_SEM_CLASSES = 6

# Roadmap colours per class (RGB), as in the reference's bird-eye view: black terrain, dark road.
SEM_COLORS = np.array([
    [0, 0, 0],  # offroad
    [60, 60, 64],  # road
    [130, 130, 130],  # sidewalk
    [230, 230, 230],  # white lane divider
    [230, 200, 40],  # yellow centre line
    [255, 255, 255],  # stop line
], dtype=np.uint8)


class Town(NamedTuple):
    """A built town. Field names marked (sensors) are relied on by ``sensors.py``: do not rename.

    sem_map (sensors): uint8 [Hm, Wm], SEM_* class of each cell. Cell (i, j) has its centre at town
        (x, y) = map_origin_m + ((j + 0.5), (i + 0.5)) * map_res_m, so row index grows with y (north).
    map_origin_m (sensors): float32 [2], town (x, y) of the corner of cell (0, 0).
    map_res_m (sensors): float32 [], metres per cell.
    building_box (sensors): float32 [NB, 5], (x, y, yaw, length, width) of buildings and landmarks.
    building_height_m (sensors): float32 [NB].
    building_color (sensors): uint8 [NB, 3].
    """
    sem_map: np.ndarray
    map_origin_m: np.ndarray
    map_res_m: np.ndarray
    building_box: np.ndarray
    building_height_m: np.ndarray
    building_color: np.ndarray
