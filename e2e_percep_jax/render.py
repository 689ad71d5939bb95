"""Top-down pictures of the town and its traffic, for people to look at (host-side NumPy + cv2).

Usage: ``view = TopDown(town, window_m, px_per_m)`` draws the static town once; ``view.draw(state)`` returns
an RGB image [H, W, 3] with lights and vehicles on it. North is up.
"""
import cv2
import jax.numpy as jnp
import numpy as np

from e2e_percep_jax import geometry as geo
from e2e_percep_jax import motion
from e2e_percep_jax import town as town_lib

# Display colours per semantic class (RGB); the terrain is greener than the roadmap's black.
_SEM_VIEW = np.array([[38, 52, 38], [62, 62, 66], [140, 140, 136], [230, 230, 230], [230, 200, 40],
                      [255, 255, 255]], np.uint8)
_LIGHT_RGB = {town_lib.LIGHT_RED: (230, 30, 30), town_lib.LIGHT_YELLOW: (250, 200, 0),
              town_lib.LIGHT_GREEN: (40, 220, 60)}
_EGO_RGB = (255, 0, 255)
_SHIFT = 4  # cv2 fractional bits


class TopDown:
    """A north-up view of the town window ``window_m = (x_min, y_min, x_max, y_max)`` (whole town if None)."""

    def __init__(self, town, window_m=None, px_per_m=2.0, draw_lanes=False):
        self.town = town
        sem = np.asarray(town.sem_map)
        res, origin = float(town.map_res_m), np.asarray(town.map_origin_m, np.float64)
        if window_m is None:  # the road network and its building belt, without the empty margin
            node_xy = np.asarray(town.node_xy_m)
            pad = town_lib.BUILDING_BELT_M + 5.0
            window_m = (*(node_xy.min(0) - pad), *(node_xy.max(0) + pad))
        self.x0, self.y0, x1, self.y1 = map(float, window_m)
        self.ppm = px_per_m
        size = (int(round((x1 - self.x0) * px_per_m)), int(round((self.y1 - self.y0) * px_per_m)))
        # Each output pixel takes the class of the map cell under its centre (north up: rows run south).
        cols = ((self.x0 + (np.arange(size[0]) + 0.5) / px_per_m - origin[0]) / res).astype(int)
        rows = ((self.y1 - (np.arange(size[1]) + 0.5) / px_per_m - origin[1]) / res).astype(int)
        inside_r = (rows >= 0) & (rows < sem.shape[0])
        inside_c = (cols >= 0) & (cols < sem.shape[1])
        classes = np.zeros((size[1], size[0]), np.uint8)
        classes[np.ix_(inside_r, inside_c)] = sem[np.ix_(rows[inside_r], cols[inside_c])]
        self.background = _SEM_VIEW[classes]
        if draw_lanes:
            for xy, length in zip(np.asarray(town.lane_xy_m), np.asarray(town.lane_length_m)):
                n = int(np.ceil(length / town_lib.LANE_DS_M)) + 1
                cv2.polylines(self.background, [self._px(xy[:n])], False, (90, 120, 160), 1, cv2.LINE_AA, _SHIFT)
        boxes = np.asarray(town.building_box)
        order = np.argsort(np.asarray(town.building_height_m))  # tall ones on top
        for i in order:
            color = tuple(int(c) for c in np.asarray(town.building_color)[i])
            self._box(self.background, boxes[i], color, outline=tuple(int(c * 0.55) for c in color))

    def _px(self, xy):
        xy = np.asarray(xy, np.float64)
        px = np.stack([(xy[..., 0] - self.x0) * self.ppm, (self.y1 - xy[..., 1]) * self.ppm], -1)
        return np.round(px * (1 << _SHIFT)).astype(np.int32)

    def _box(self, img, box, color, outline, thickness=1):
        # float32 on XLA: NumPy's float32 cos / sin round differently, and the pictures are pinned to these
        corners = self._px(np.asarray(geo.box_corners(jnp.asarray(box, jnp.float32))))
        cv2.fillPoly(img, [corners], color, cv2.LINE_AA, _SHIFT)
        cv2.polylines(img, [corners], True, outline, thickness, cv2.LINE_AA, _SHIFT)

    def draw(self, state=None, time_s=None):
        """The town with its lights at ``time_s`` (default: the state's time) and the state's vehicles."""
        img = self.background.copy()
        if state is None:
            return img
        if time_s is None:
            time_s = float(state.step) * motion.DT_S
        lights = np.asarray(town_lib.light_states(self.town, time_s))
        radius = int(max(1.2 * self.ppm, 2) * (1 << _SHIFT))
        for xy, light in zip(self._px(np.asarray(self.town.light_xy_m)), lights):
            cv2.circle(img, tuple(xy), radius, _LIGHT_RGB[int(light)], -1, cv2.LINE_AA, _SHIFT)
        boxes, colors = np.asarray(state.veh_box), np.asarray(state.veh_color)
        for i, (box, color) in enumerate(zip(boxes, colors)):
            ego = i == 0
            self._box(img, box, tuple(int(c) for c in color), outline=_EGO_RGB if ego else (0, 0, 0),
                      thickness=2 if ego else 1)
            nose = box[:2] + 0.4 * box[3] * np.array([np.cos(box[2]), np.sin(box[2])])
            cv2.line(img, tuple(self._px(box[:2])), tuple(self._px(nose)), (0, 0, 0), 1, cv2.LINE_AA, _SHIFT)
        return img
