"""Sensor kinds for scenario files.

Each module here registers its kind(s) with
:func:`dfusion.sim.scenario.register_sensor` when imported; importing this
package (which :func:`dfusion.sim.scenario.load_scenario` does) makes every kind
available. Add one import line per module below.
"""
from . import camera  # noqa: F401  (sensor kind "camera")
from . import wsn  # noqa: F401  (sensor kind "wsn_rssi")
from . import robot  # noqa: F401  (sensor kinds "robot_mcl", "robot_icp", "robot_env_camera")
