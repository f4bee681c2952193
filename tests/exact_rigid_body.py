"""The exact motion of the torque-free rigid body, for tests (NumPy/SciPy only).

Body angular velocity (Jacobi elliptic functions), for principal moments
``J1 < J2 < J3``, energy ``E = 1/2 Omega . J Omega`` and ``L = |J Omega|``:

- ``L^2 > 2 E J2`` (the body tumbles around the J3 axis):
  ``Omega = (A1 cn u, A2 sn u, s A3 dn u)``,
  ``A1^2 = (2E J3 - L^2) / (J1 (J3 - J1))``,
  ``A2^2 = (2E J3 - L^2) / (J2 (J3 - J2))``,
  ``A3^2 = (L^2 - 2E J1) / (J3 (J3 - J1))``,
  ``lambda^2 = (J3 - J2)(L^2 - 2E J1) / (J1 J2 J3)``,
  ``m = k^2 = (J2 - J1)(2E J3 - L^2) / ((J3 - J2)(L^2 - 2E J1))``;
- ``L^2 < 2 E J2`` (around the J1 axis):
  ``Omega = (s A1 dn u, A2 sn u, A3 cn u)``, with the same ``A1``, ``A3``,
  ``A2^2 = (L^2 - 2E J1) / (J2 (J2 - J1))``,
  ``lambda^2 = (J2 - J1)(2E J3 - L^2) / (J1 J2 J3)``,
  ``m = (J3 - J2)(L^2 - 2E J1) / ((J2 - J1)(2E J3 - L^2))``;

where ``u = s lambda t + u0`` and ``s = +-1`` is the (constant) sign of the
``dn`` component. Substituting into Euler's equations
``J1 Omega1' = (J2 - J3) Omega2 Omega3`` (and cyclic) with ``sn' = cn dn``,
``cn' = -sn dn``, ``dn' = -m sn cn`` fixes the signs as written; ``u0`` is the
incomplete elliptic integral of the amplitude ``atan2(sn u0, cn u0)``.

Attitude: the spatial momentum ``pi = R J Omega`` is constant. In a spatial
frame whose third axis is ``pi / L``, write ``R = Rz(phi) Rx(theta) Rz(psi)``
(z-x-z Euler angles, body to space). Then ``J Omega = R^T pi`` gives
``J Omega = L (sin theta sin psi, sin theta cos psi, cos theta)``, which fixes
``theta`` and ``psi`` from ``Omega`` alone, and projecting the angular
velocity gives the precession rate
``phi' = L (J1 Omega1^2 + J2 Omega2^2) / (J1^2 Omega1^2 + J2^2 Omega2^2)``,
a smooth positive function integrated by adaptive quadrature.

References: L. D. Landau, E. M. Lifshitz, *Mechanics*, 3rd ed., sec. 37;
E. T. Whittaker, *Analytical Dynamics*, sec. 69.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.integrate import IntegrationWarning, quad, solve_ivp
from scipy.special import ellipj, ellipkinc


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack(
        [np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2
    )


def hat(w):
    w = np.asarray(w, dtype=np.float64)
    z = np.zeros_like(w[..., 0])
    return np.stack(
        [
            np.stack([z, -w[..., 2], w[..., 1]], -1),
            np.stack([w[..., 2], z, -w[..., 0]], -1),
            np.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def euler_rhs(J, Omega, M=None):
    """``Omega' = J^-1 (M - Omega x J Omega)`` for principal moments ``J`` (NumPy)."""
    J = np.asarray(J, dtype=np.float64)
    rhs = -np.cross(Omega, J * Omega)
    if M is not None:
        rhs = rhs + M
    return rhs / J


class ExactFreeBody:
    """The exact torque-free motion ``(R(t), Omega(t))`` from ``(R0, Omega0)``.

    **Arguments:**

    - `moments`: principal moments ``J1 < J2 < J3`` (strictly increasing), shape `(3,)`.
    - `R0`: initial attitude, shape `(3, 3)`.
    - `Omega0`: initial body angular velocity, shape `(3,)`, not on the separatrix
      ``|J Omega|^2 = 2 E J2``.
    """

    def __init__(self, moments, R0, Omega0):
        J = np.asarray(moments, dtype=np.float64)
        if J.shape != (3,) or not (0 < J[0] < J[1] < J[2]):
            raise ValueError(f"moments must satisfy 0 < J1 < J2 < J3, got {J}")
        W0 = np.asarray(Omega0, dtype=np.float64)
        self.J, self.R0, self.Omega0 = J, np.asarray(R0, dtype=np.float64), W0
        J1, J2, J3 = J
        two_E = float(np.sum(J * W0**2))
        L2 = float(np.sum((J * W0) ** 2))
        self.energy, self.L = 0.5 * two_E, np.sqrt(L2)
        p = two_E * J3 - L2  # >= 0
        q = L2 - two_E * J1  # >= 0
        A1 = np.sqrt(p / (J1 * (J3 - J1)))
        A3 = np.sqrt(q / (J3 * (J3 - J1)))
        if L2 > two_E * J2:  # around the J3 axis: cn in 1, dn in 3
            self.cn_axis, self.dn_axis = 0, 2
            A2 = np.sqrt(p / (J2 * (J3 - J2)))
            lam = np.sqrt((J3 - J2) * q / (J1 * J2 * J3))
            m = (J2 - J1) * p / ((J3 - J2) * q)
            A = np.array([A1, A2, A3])
        elif L2 < two_E * J2:  # around the J1 axis: dn in 1, cn in 3
            self.cn_axis, self.dn_axis = 2, 0
            A2 = np.sqrt(q / (J2 * (J2 - J1)))
            lam = np.sqrt((J2 - J1) * p / (J1 * J2 * J3))
            m = (J3 - J2) * q / ((J2 - J1) * p)
            A = np.array([A1, A2, A3])
        else:
            raise ValueError("Omega0 lies on the separatrix L^2 = 2 E J2")
        if not 0 <= m < 1:
            raise ValueError(f"elliptic modulus m = {m} outside [0, 1)")
        self.A, self.m = A, m
        self.sign = 1.0 if W0[self.dn_axis] >= 0 else -1.0
        self.rate = self.sign * lam
        amp0 = np.arctan2(W0[1] / A[1], W0[self.cn_axis] / A[self.cn_axis])
        self.u0 = ellipkinc(amp0, m)
        # Frame with pi along e3: R = Q Rz(phi) Rx(theta) Rz(psi), phi(0) = 0.
        self.Q = self.R0 @ self._euler_part(W0).T

    def omega(self, t):
        """Body angular velocity at times ``t``, shape ``t.shape + (3,)``."""
        t = np.asarray(t, dtype=np.float64)
        sn, cn, dn, _ = ellipj(self.rate * t + self.u0, self.m)
        out = np.empty(t.shape + (3,))
        out[..., self.cn_axis] = self.A[self.cn_axis] * cn
        out[..., 1] = self.A[1] * sn
        out[..., self.dn_axis] = self.sign * self.A[self.dn_axis] * dn
        return out

    def _euler_part(self, W):
        """``Rx(theta) Rz(psi)`` from the body momentum ``J Omega = L R^T e3``."""
        Pi = self.J * W
        theta = np.arccos(np.clip(Pi[..., 2] / self.L, -1.0, 1.0))
        psi = np.arctan2(Pi[..., 0], Pi[..., 1])
        return _rx(theta) @ _rz(psi)

    def precession_rate(self, t):
        """``phi'(t) = L (J1 W1^2 + J2 W2^2) / (J1^2 W1^2 + J2^2 W2^2)``."""
        W = self.omega(t)
        J1, J2, _ = self.J
        num = J1 * W[..., 0] ** 2 + J2 * W[..., 1] ** 2
        den = (J1 * W[..., 0]) ** 2 + (J2 * W[..., 1]) ** 2
        return self.L * num / den

    def precession_angle(self, t):
        """``phi(t) = int_0^t phi'``, by adaptive Gauss–Kronrod quadrature (1-D ``t``)."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        order = np.argsort(t)
        out = np.empty_like(t)
        acc, prev = 0.0, 0.0
        for i in order:
            if t[i] != prev:
                with warnings.catch_warnings():
                    # Near-eps tolerances make QUADPACK warn about round-off; the
                    # result is checked against DOP853 in tests/test_dynamics.py.
                    warnings.simplefilter("ignore", IntegrationWarning)
                    val, _ = quad(
                        self.precession_rate, prev, t[i], epsabs=1e-15, epsrel=1e-14, limit=500
                    )
                acc += val
                prev = t[i]
            out[i] = acc
        return out

    def attitude(self, t):
        """Attitude at times ``t`` (scalar or 1-D), shape ``t.shape + (3, 3)``."""
        t = np.asarray(t, dtype=np.float64)
        flat = np.atleast_1d(t)
        phi = self.precession_angle(flat)
        R = self.Q @ _rz(phi) @ self._euler_part(self.omega(flat))
        return R.reshape(t.shape + (3, 3))

    def state(self, t):
        """``(R(t), Omega(t))``."""
        return self.attitude(t), self.omega(t)


def ambient_reference(moments, R0, Omega0, t_eval, torque=None, rtol=1e-13, atol=1e-13):
    """DOP853 solution of ``R' = R hat(Omega)``, ``J Omega' = M(t) - Omega x J Omega``.

    Integrated in ``R^9 x R^3`` (no group structure) at tight tolerances.

    **Arguments:**

    - `moments`: principal moments, shape `(3,)`.
    - `R0`, `Omega0`: initial state.
    - `t_eval`: increasing output times, shape `(n,)` (``t_eval[0]`` is the start).
    - `torque`: ``t -> M(t)`` (NumPy), or ``None``.

    **Returns:** ``(R, Omega)`` with shapes `(n, 3, 3)` and `(n, 3)`.
    """
    J = np.asarray(moments, dtype=np.float64)
    t_eval = np.atleast_1d(np.asarray(t_eval, dtype=np.float64))

    def f(t, y):
        R, W = y[:9].reshape(3, 3), y[9:]
        dW = euler_rhs(J, W, None if torque is None else np.asarray(torque(t)))
        return np.concatenate([(R @ hat(W)).ravel(), dW])

    y = np.concatenate([np.asarray(R0, dtype=np.float64).ravel(), np.asarray(Omega0, float)])
    out = [y]
    for ta, tb in zip(t_eval[:-1], t_eval[1:], strict=True):
        # Restart at every output time: no dense-output interpolation error.
        sol = solve_ivp(f, (ta, tb), y, method="DOP853", rtol=rtol, atol=atol)
        if not sol.success:  # pragma: no cover
            raise RuntimeError(sol.message)
        y = sol.y[:, -1]
        out.append(y)
    out = np.array(out)
    return out[:, :9].reshape(-1, 3, 3), out[:, 9:]
