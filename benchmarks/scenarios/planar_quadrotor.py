"""A planar quadrotor, n = 6, m = 2: the benchmarks' n = 6 scaling case.

State ``x = [p_x, p_z, theta, v_x, v_z, omega]``, inputs the two rotor thrusts
``u = [u_1, u_2]`` (N); mass 0.486 kg, inertia 0.00383 kg m^2 and arm 0.25 m
(the parameters of Drake's ``QuadrotorPlant``, in the plane)::

    p' = v,  theta' = omega,
    v_x' = -sin(theta) (u_1 + u_2) / m,  v_z' = cos(theta) (u_1 + u_2) / m - g,
    omega' = arm (u_1 - u_2) / I.

Written with numpy functions and no branch on the state, so ``f`` and ``g``
trace symbolically (Jacobian bounds, and the C++ symbolic blocks).
"""

from __future__ import annotations

import numpy as np

from ofrl_drake import ControlAffineSystem

MASS = 0.486
INERTIA = 0.00383
ARM = 0.25
GRAVITY = 9.81


def f(x: np.ndarray) -> np.ndarray:
    """Drift: the kinematics and gravity; (6,) or a batch (6, N)."""
    zero = 0 * x[0]
    return np.array([x[3], x[4], x[5], zero, zero - GRAVITY, zero])


def g(x: np.ndarray) -> np.ndarray:
    """Input matrix, (6, 2) or (6, 2, N)."""
    zero = 0 * x[0]
    s = np.sin(x[2]) / MASS
    c = np.cos(x[2]) / MASS
    spin = zero + ARM / INERTIA
    return np.array([[zero, zero], [zero, zero], [zero, zero], [-s, -s], [c, c], [spin, -spin]])


def make_plant() -> ControlAffineSystem:
    """The planar quadrotor; C measures the position and the attitude."""
    C = np.hstack([np.eye(3), np.zeros((3, 3))])
    return ControlAffineSystem(f, g, C, name="planar_quadrotor")
