"""The constants of the vehicles' motion, shared by the world that moves them and the estimators that
follow them (the pose belief's filter, dead reckoning) without needing the world or the town."""

DT_S = 0.1  # the world's time step (s): one frame
WHEELBASE_M = 2.7  # the kinematic bicycle model's wheelbase
