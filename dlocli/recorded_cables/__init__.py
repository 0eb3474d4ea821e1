"""Recorded cables in: the readers of recorded trajectory files (DEFORM's pickles, arrays,
CSV, ROS 2 bags), their timing and gaps, and `dlo import`, which writes them as a marker
dataset (:mod:`dlocli.data.markers`; scored by :mod:`dlocli.data.protocol`).

A marker dataset holds positions only; some markers are *held* (a gripper moves them), and
their recorded motion is the input of every step (a boundary condition per marker); the
other markers are the state to predict.
"""
