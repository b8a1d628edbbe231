"""Scenario files the tests of live nodes share."""

#: A robot with a position sensor and a sensorless base, linked (``str.format(duration=...)``).
TWO_NODES = """duration = {duration}
dt = 0.1
[target]
motion = "constant_velocity"
initial_mean = [0.0, 0.0, 0.0, 0.0]
initial_cov_diag = [1.0, 1.0, 1.0, 1.0]
[[nodes]]
name = "robot"
sensor = "position"
std = 1.0
[[nodes]]
name = "base"
[[links]]
between = ["robot", "base"]
"""
