"""Lee's quadrotor hovering at a fixed point, for tests (NumPy/SciPy only).

The model and controller of Lee, Leok & McClamroch, "Geometric tracking control
of a quadrotor UAV on SE(3)", CDC 2010, with ``e3`` pointing down and the thrust
along ``-R e3``:

    x' = v,   m v' = m g e3 - f R e3,   R' = R hat(Omega),   J Omega' = M - Omega x J Omega,

for a constant desired position ``x_d = 0`` and heading ``b1_d = e1``:

- ``A = -k_x x - k_v v - m g e3``, ``f = -A . R e3`` (the paper's (12), (15));
- ``Rc = F(A) = [b1c, b2c, b3c]`` with ``b3c = -A/|A|``,
  ``b2c = b3c x b1_d / |b3c x b1_d|``, ``b1c = b2c x b3c``;
- ``M = -k_R e_R - k_Omega e_Omega + Omega x J Omega
  - J (hat(Omega) R^T Rc Omega_c - R^T Rc dOmega_c)`` (16), with
  ``e_R = 1/2 vee(Rc^T R - R^T Rc)``, ``e_Omega = Omega - R^T Rc Omega_c``,
  ``hat(Omega_c) = Rc^T Rc'``, ``dOmega_c = vee(skew(Rc^T Rc''))``.

The commanded rates are *not* taken from a hand-written chain rule through the
unit vectors (as `so3jax.quadrotor_control` and ``tests/test_quadrotor.py`` do):
``Rc`` depends on the state through ``A`` alone, and along the closed loop

    A' = -k_x v - k_v v',          v' = g e3 - (f/m) R e3,
    A'' = -k_x v' - k_v v'',       v'' = -(f' R e3 + f R hat(Omega) e3) / m,
    f' = -A' . R e3 - A . R hat(Omega) e3

(no ``Omega'``: the torque does not feed back into ``Rc''``). The path
``P(s) = A + s A' + s^2/2 A''`` agrees with ``A(t + s)`` to second order, so
``Rc'`` and ``Rc''`` are the first two derivatives of ``s -> F(P(s))`` at ``s = 0``,
here by fourth-order central differences with step ``h``: truncation
``~ h^4 |d^6 F(P)/ds^6| / 90``, round-off ``~ eps / h^2``. With ``h = 5e-4`` s, on
the recovery's path (``|Omega_c|`` up to 3.6 rad/s, ``|dOmega_c|`` up to 16 rad/s^2)
they differ from the exact rates by about ``1e-10`` rad/s and ``1e-9`` rad/s^2.

Integrated in ``R^3 x R^3 x R^9 x R^3`` (``R`` unconstrained, drifting off
SO(3) by the integrator's tolerance only) by `scipy.integrate.solve_ivp` with
DOP853.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

E1 = np.array([1.0, 0.0, 0.0])
E3 = np.array([0.0, 0.0, 1.0])
#: Fourth-order central differences on the points s = -2h, -h, 0, h, 2h.
_D1 = np.array([1.0, -8.0, 0.0, 8.0, -1.0]) / 12.0
_D2 = np.array([-1.0, 16.0, -30.0, 16.0, -1.0]) / 12.0
_S = np.array([-2.0, -1.0, 0.0, 1.0, 2.0])


def hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def vee_skew(W):
    """``vee`` of the skew part of ``W``."""
    return 0.5 * np.array([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]])


def commanded_attitude(A):
    """``Rc = F(A)`` for a batch of ``A`` (shape ``(..., 3)``), with ``b1_d = e1``."""
    b3 = -A / np.linalg.norm(A, axis=-1, keepdims=True)
    c = np.cross(b3, E1)
    b2 = c / np.linalg.norm(c, axis=-1, keepdims=True)
    b1 = np.cross(b2, b3)
    return np.stack([b1, b2, b3], axis=-1)


class HoverReference:
    """The closed loop of Lee's controller regulating the position to the origin.

    **Arguments:** ``mass``, ``inertia`` (3 principal moments), ``gains``
    ``(k_x, k_v, k_R, k_Omega)`` (scalars), ``g``, and ``h`` the step of the
    differences that give ``Rc'`` and ``Rc''``.
    """

    def __init__(self, mass, inertia, gains, g=9.81, h=5e-4):
        self.m, self.J = float(mass), np.diag(inertia)
        self.kx, self.kv, self.kR, self.kW = (float(k) for k in gains)
        self.g, self.h = float(g), float(h)

    def control(self, x, v, R, W):
        """``(f, M, Rc, Omega_c, dOmega_c, Psi)`` at one state."""
        m, g, kx, kv = self.m, self.g, self.kx, self.kv
        A = -kx * x - kv * v - m * g * E3
        Re3, Re3_1 = R @ E3, R @ np.cross(W, E3)
        f = -A @ Re3
        dv = g * E3 - f / m * Re3
        A1 = -kx * v - kv * dv
        f1 = -A1 @ Re3 - A @ Re3_1
        A2 = -kx * dv + kv * (f1 * Re3 + f * Re3_1) / m
        s = self.h * _S
        Rcs = commanded_attitude(A + s[:, None] * A1 + 0.5 * (s**2)[:, None] * A2)
        Rc = Rcs[2]
        Rc1 = np.tensordot(_D1, Rcs, 1) / self.h
        Rc2 = np.tensordot(_D2, Rcs, 1) / self.h**2
        Wc, dWc = vee_skew(Rc.T @ Rc1), vee_skew(Rc.T @ Rc2)
        RtRc = R.T @ Rc
        eR = vee_skew(Rc.T @ R)  # 1/2 vee(Rc^T R - R^T Rc)
        eW = W - RtRc @ Wc
        J = self.J
        M = (
            -self.kR * eR
            - self.kW * eW
            + np.cross(W, J @ W)
            - J @ (hat(W) @ RtRc @ Wc - RtRc @ dWc)
        )
        Psi = 0.5 * (3.0 - np.trace(RtRc))
        return f, M, Rc, Wc, dWc, Psi

    def rhs(self, t, y):
        x, v, R, W = y[0:3], y[3:6], y[6:15].reshape(3, 3), y[15:18]
        f, M, *_ = self.control(x, v, R, W)
        dv = self.g * E3 - f / self.m * (R @ E3)
        dW = np.linalg.solve(self.J, M - np.cross(W, self.J @ W))
        return np.concatenate([v, dv, (R @ hat(W)).ravel(), dW])

    def solve(self, R0, t_end, x0=(0.0, 0.0, 0.0), v0=(0.0, 0.0, 0.0), W0=(0.0, 0.0, 0.0),
              tol=1e-12):  # fmt: skip
        """DOP853 from ``(x0, v0, R0, W0)`` over ``[0, t_end]``, with dense output."""
        y0 = np.concatenate([x0, v0, np.asarray(R0, float).ravel(), W0])
        sol = solve_ivp(
            self.rhs, (0.0, t_end), y0, method="DOP853", rtol=tol, atol=tol, dense_output=True
        )
        assert sol.success, sol.message
        return sol

    def psi(self, y):
        """``Psi(R, Rc)`` at a state vector ``y``."""
        return self.control(y[0:3], y[3:6], y[6:15].reshape(3, 3), y[15:18])[-1]
