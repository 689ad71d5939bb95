"""Where every town lies (town frame, metres), apart from the town's builder (``town.py``, which needs
OpenCV) so that the pose belief reads it in a process that only infers.

A town is a jittered grid of GRID_NODES nodes GRID_SPACING_M apart from the origin, with buildings up to
BUILDING_BELT_M outside its perimeter road. The square [AREA_ORIGIN_M, AREA_ORIGIN_M + AREA_SIZE_M) holds
all of it: the node grid's span (7 x 60 m by 6 x 70 m) with the belt on each side. Its lanes, jittered
nodes and curves included, stay 10 m or more inside it; the pose belief's grid covers it.
"""

GRID_NODES = (8, 7)
GRID_SPACING_M = (60.0, 70.0)
BUILDING_BELT_M = 30.0  # buildings also stand this far outside the perimeter road
AREA_ORIGIN_M = -BUILDING_BELT_M
AREA_SIZE_M = max((n - 1) * s for n, s in zip(GRID_NODES, GRID_SPACING_M)) + 2 * BUILDING_BELT_M
