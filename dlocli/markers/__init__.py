"""Marker-form data: what real setups observe (tracked marker positions only, any marker
count), the reader of recorded trajectory files, and the DEFORM benchmark protocol.

A marker dataset holds positions only; some markers are *held* (a gripper moves them), and
their recorded motion is the input of every step (a boundary condition per marker); the
other markers are the state to predict.
"""
