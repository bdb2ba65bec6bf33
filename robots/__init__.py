"""Arm kinematic models and robot backends (the simulated robot and its world)."""
