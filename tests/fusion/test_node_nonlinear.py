"""A fusion node with a nonlinear model whose heading crosses ±pi, against filterpy's EKF."""
from __future__ import annotations

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from dfusion.fusion import FusionNode
from dfusion.models import MeasurementModel, Unicycle


class HeadingVector(MeasurementModel):
    """z = (cos theta, sin theta): a compass whose Jacobian depends on the heading."""

    dim_z = 2
    is_linear = False

    def h(self, x):
        return np.array([np.cos(x[2]), np.sin(x[2])])

    def H(self, x):
        return np.array([[0.0, 0.0, -np.sin(x[2])], [0.0, 0.0, np.cos(x[2])]])

    @property
    def R(self):
        return np.eye(2) * 0.05**2


def test_node_linearizes_at_the_continuous_heading():
    motion = Unicycle(std_v=0.2, std_w=0.1)
    sensor = HeadingVector()
    x0, P0 = np.array([0.0, 0.0, 2.9]), np.diag([0.1, 0.1, 0.05])
    node = FusionNode("a", [], motion, window=50, prior=(0.0, x0, P0))
    ekf = ExtendedKalmanFilter(dim_x=3, dim_z=2)
    ekf.x, ekf.P = x0.reshape(3, 1).copy(), P0.copy()
    u = np.array([1.0, 0.4])   # turning left: the heading goes past +pi
    rng = np.random.default_rng(2)
    truth = x0.copy()
    for k in range(1, 16):
        t = 0.25 * k
        truth = motion.f(truth, 0.25, u)
        z = sensor.h(truth) + rng.normal(0, 0.05, 2)
        node.predict(t, u)
        node.update(t, z, sensor)
        x = ekf.x.ravel()
        ekf.F = motion.F(0.25, x, u)
        ekf.Q = motion.Q(0.25, x, u)
        ekf.x = motion.f(x, 0.25, u).reshape(3, 1)
        ekf.P = ekf.F @ ekf.P @ ekf.F.T + ekf.Q
        ekf.update(z.reshape(2, 1), HJacobian=lambda xx: sensor.H(xx.ravel()), Hx=lambda xx: sensor.h(xx.ravel()).reshape(2, 1), R=sensor.R)
    assert truth[2] < 0.0   # started at 2.9 rad turning left: the heading went past +pi and wrapped
    m, P = node.estimate()
    ref = ekf.x.ravel().copy()
    ref[2] = (ref[2] + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(m, ref, atol=1e-9)
    np.testing.assert_allclose(P, ekf.P, atol=1e-9)
