"""A dfusion plug-in: sensor kind "range_beacon", a radio beacon measuring its distance to the target."""
import numpy as np

from dfusion.models import MeasurementModel
from dfusion.scenario import SensorKind
from dfusion.scenario.values import number, vector


class BeaconRange(MeasurementModel):
    """z = |p - b| + v, v ~ N(0, std^2): the distance from beacon b to the position p = x[:2]."""

    dim_z = 1

    def __init__(self, beacon, std):
        self.beacon, self.std = np.asarray(beacon, dtype=float), float(std)

    def h(self, x):
        return np.array([np.hypot(*(x[:2] - self.beacon))])

    def H(self, x):
        d = x[:2] - self.beacon
        J = np.zeros((1, len(x)))
        J[0, :2] = d / max(np.hypot(*d), 1e-9)
        return J

    @property
    def R(self):
        return np.array([[self.std**2]])


def beacon_sensor(table, scenario):
    """The model a node table describes: beacon = [x, y] (m), std (m, default 0.3)."""
    return BeaconRange(vector(table, "beacon", (2,)), number(table, "std", 0.3, positive=True))


# no front end: the node fuses each range with an EIF update of BeaconRange
SENSOR_KINDS = {"range_beacon": SensorKind("range_beacon", frozenset({"beacon", "std"}), beacon_sensor,
                                           doc="distance from a fixed radio beacon to the target (m)")}
