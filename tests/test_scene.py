"""The hand-built drive behind a kerb building (``sim.scene``), on the training town, checked frame by frame."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from e2e_percep_jax import config as config_lib
from e2e_percep_jax import metrics
from e2e_percep_jax.sim import geometry as geo
from e2e_percep_jax.sim import rollout, scene, sensors, world
from e2e_percep_jax.sim import town as town_lib


@pytest.mark.slow
def test_the_kerb_building_hides_the_vehicle_after_the_lidar_saw_it_and_nothing_else_is_in_view():
    """Town 0's drive: the added building stands off the road and is the only change to the town; the ego
    stands; the vehicle is the only one in view; the sensors see it for at least SEEN_FRAMES frames, then
    lidar → (camera only) → remembered until it leaves the view, and in every remembered frame the lidar's line
    of sight to its centre crosses the added building first (``sensors.sight_blocker``, plan geometry)."""
    cfg = config_lib.get_config("cpu")
    town = town_lib.build_town(cfg.world.town_seed)
    drive = scene.kerb_building_drive(town, world.reset(jax.random.PRNGKey(0), town, cfg.world), speed_mps=3.0)
    nb = town.building_box.shape[0]
    assert drive.town.building_box.shape[0] == nb + 1
    np.testing.assert_array_equal(np.asarray(drive.town.building_box[:nb]), np.asarray(town.building_box))
    added = np.asarray(drive.town.building_box[nb], np.float64)
    corners = np.asarray(geo.box_corners(jnp.asarray(added)))
    inside = corners.mean(0) + 0.95 * (corners - corners.mean(0))  # just inside its corners, and its centre
    for x, y in np.concatenate([inside, corners.mean(0)[None]]):
        assert int(sensors.sem_classes_at(town, x, y)[0]) != town_lib.SEM_ROAD
    ego = np.stack([np.asarray(s.veh_box[world.EGO]) for s in drive.states])
    assert np.all(ego == ego[0])

    frames = scene.observe_drive(drive, cfg.data.image_size)
    valid = np.stack([f["boxes_valid"] for f in frames])
    assert not valid[:, 1:].any()  # no other vehicle in view
    seen = {k: jnp.stack([f[k] for f in frames]) for k in ("boxes_lidar_visible", "boxes_camera_visible")}
    group = np.asarray(metrics.box_groups(*seen.values(), rollout.frames_since_seen(seen)))[:, 0]
    names = [metrics.GROUPS[g] if v else "out" for g, v in zip(group, valid[:, 0])]
    remembered = [f for f, n in enumerate(names) if n == "remembered"]
    assert len(remembered) >= 5
    first, last = remembered[0], remembered[-1]
    assert remembered == list(range(first, last + 1)) and set(names[last + 1 :]) == {"out"}
    last_lidar = max(f for f, n in enumerate(names) if n == "lidar")
    assert last_lidar < first and set(names[last_lidar + 1 : first]) <= {"camera_only"}
    assert names[last_lidar + 1 - scene.SEEN_FRAMES : last_lidar + 1] == ["lidar"] * scene.SEEN_FRAMES
    for f in remembered:
        pose = frames[f]["pose"]
        buildings = geo.box_to_ego(np.asarray(drive.town.building_box, np.float64), pose[:2], geo.pose_yaw(pose))
        assert sensors.sight_blocker(frames[f]["boxes"][0], frames[f]["boxes"], buildings) == ("town", nb), f
