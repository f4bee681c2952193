"""Integral action of the quadrotor's controller (Goodarzi, Lee & Lee, ECC 2013).

A vehicle with drag hovers in a constant wind. Without integral action its position
error settles at the equilibrium of the closed loop, found here independently: Lee's
controller written out in NumPy (hand-written chain rules, as in
``tests/test_quadrotor_rotors.py``) and the equilibrium ``v' = 0``, ``Omega' = 0`` solved
by `scipy.optimize.root`. The force balance alone, ``e_x = R diag(d) R^T w / k_x``,
misses part of it: the controller's model has no drag, so at rest it reads an
acceleration ``-F_d / m`` that is not there, commands an ``Rc`` turning at
``Omega_c != 0``, and its attitude loop settles at ``k_R e_R = k_Omega Omega_c + J
dOmega_c``: a tilt that adds ``(k_Omega k_v + J k_x) / (k_R m)`` times the horizontal
drag force (to first order). With integral action the error goes to zero.
"""

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import root
from scipy.spatial.transform import Rotation

import so3jax as s
from so3jax import scenes
from so3jax._control import _geometric_torque
from so3jax._quadrotor import (
    _COUNTER,
    _HELD,
    _N,
    DIFFTUNE_INERTIA,
    DIFFTUNE_MASS,
    QuadrotorControl,
    QuadrotorPlant,
    _commanded_attitude,
    _control_of,
    _e3,
    _sample_control,
    _time_derivatives,
)
from so3jax._so3 import _cross, _dot, _mm, _mT, _mv, _vee
from so3jax._state import LieState, LieTangent

M_, J_ = DIFFTUNE_MASS, np.diag(DIFFTUNE_INERTIA)
K = np.array([16.0, 12.0, 8.81, 2.54])  # k_x, k_v, k_R, k_Omega: a well-damped hover
G = 9.81
E1, E3 = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
DRAG, WIND = 0.1, np.array([2.0, -1.0, 0.5])
K_I, C1, C2 = np.array([8.0, 2.0]), 2.0, 4.0  # (k_i, k_I) where integral action is on
DT, N_STEPS = 0.01, 700


def np_hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def np_vee(W):
    return 0.5 * np.array([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]])


def unit_d2(a, a1, a2):
    n = np.linalg.norm(a)
    u = a / n
    n1 = u @ a1
    u1 = (a1 - u * n1) / n
    n2 = u1 @ a1 + u @ a2
    return u, u1, (a2 - 2 * u1 * n1 - u * n2) / n


def np_control(x, v, R, W):
    """Lee's controller (CDC 2010, eqs. (12)-(16)) hovering at the origin, ``b1_d = e1``,
    with its nominal model ``e_v' = g e3 - f R e3 / m`` (no drag)."""
    kx, kv, kR, kW = K
    A = -kx * x - kv * v - M_ * G * E3
    Re3, Re3_1 = R @ E3, R @ np_hat(W) @ E3
    f = -A @ Re3
    ev1 = G * E3 - f / M_ * Re3
    A1 = -kx * v - kv * ev1
    f1 = -A1 @ Re3 - A @ Re3_1
    A2 = -kx * ev1 + kv * (f1 * Re3 + f * Re3_1) / M_
    b3, b31, b32 = unit_d2(-A, -A1, -A2)
    b2, b21, b22 = unit_d2(np.cross(b3, E1), np.cross(b31, E1), np.cross(b32, E1))
    b1 = np.cross(b2, b3)
    b11 = np.cross(b21, b3) + np.cross(b2, b31)
    b12 = np.cross(b22, b3) + 2 * np.cross(b21, b31) + np.cross(b2, b32)
    Rc, Rc1, Rc2 = (np.column_stack(c) for c in ((b1, b2, b3), (b11, b21, b31), (b12, b22, b32)))
    Wc, dWc = np_vee(Rc.T @ Rc1), np_vee(Rc.T @ Rc2)
    eR = np_vee(Rc.T @ R)
    eW = W - R.T @ Rc @ Wc
    M = -kR * eR - kW * eW + np.cross(W, J_ @ W) - J_ @ (np_hat(W) @ R.T @ Rc @ Wc - R.T @ Rc @ dWc)
    return f, M, Wc, dWc


def equilibrium():
    """``(x, R)`` at rest (``v = 0``, ``Omega = 0``) where the drag in the wind balances."""

    def residual(p):
        x, R = p[:3], Rotation.from_rotvec(p[3:]).as_matrix()
        f, M, _, _ = np_control(x, np.zeros(3), R, np.zeros(3))
        dv = G * E3 - f / M_ * (R @ E3) + DRAG * WIND / M_  # isotropic drag at rest
        return np.r_[dv * M_, np.linalg.solve(J_, M)]

    sol = root(residual, np.r_[DRAG * WIND / K[0], np.zeros(3)], tol=1e-14)
    assert np.abs(sol.fun).max() < 1e-12
    return sol.x[:3], Rotation.from_rotvec(sol.x[3:]).as_matrix()


def make_scene(control_period, k=K_I):
    gains = s.QuadrotorGains(*K, k_i=k[0], k_I=k[1], c1=C1, c2=C2)
    return scenes.quadrotor(
        M_,
        DIFFTUNE_INERTIA,
        gains,
        s.HoverReference(np.zeros(3)),
        drag=DRAG,
        wind=WIND,
        control_period=control_period,
    )


def _loss(k, scene):
    """Tracking cost through ``(k_i, k_I)``; aux: the last position error and status."""
    sc = eqx.tree_at(lambda q: (q.gains.k_i, q.gains.k_I), scene, (k[0], k[1]))
    tr = s.simulate(sc, s.RKMK4(), DT, N_STEPS, save_every=N_STEPS // 7)
    ex, eR = tr.extras["e_x"], tr.extras["e_R"]
    return jnp.sum(ex**2) + jnp.sum(eR**2), (ex[-1], tr.status.code)


#: One compiled program per scene structure: the value, the last position error and the
#: gradient (reverse mode), whatever ``k`` (``k = 0``: the PD controller's dynamics).
value_and_grad = eqx.filter_jit(jax.value_and_grad(_loss, has_aux=True))
#: The value alone: for continuous control, whose gradient is not checked (its reverse
#: mode compiles for as long as the rest of the module; held control's is checked).
value = eqx.filter_jit(lambda k, scene: (_loss(k, scene), None))


# ----------------------------------------------------------------------------
# Steady state in a wind, gradients
# ----------------------------------------------------------------------------


@pytest.mark.parametrize("control_period", [None, 0.01])
def test_wind_steady_state_and_gradient(control_period):
    sc = make_scene(control_period)
    assert sc.integral and sc.y0.x.shape[-1] == sc._integral_slots.stop

    # Without integral action (k_i = k_I = 0, the PD controller's dynamics): the
    # equilibrium of the closed loop.
    run = value_and_grad if control_period is not None else value
    (_, (e_pd, code)), _ = run(jnp.zeros(2), sc)
    assert int(code) == 0
    x_eq, R_eq = equilibrium()
    np.testing.assert_allclose(e_pd, x_eq, rtol=2e-4)  # settled to e^(-1.39 t)
    # the force balance alone, and the tilt of the feedforward to first order
    kx, kv, kR, kW = K
    force = R_eq @ (DRAG * WIND)
    horizontal = force * np.array([1.0, 1.0, 0.0])
    first_order = (force + (kW * kv + J_[0, 0] * kx) / (kR * M_) * horizontal) / kx
    np.testing.assert_allclose(x_eq, first_order, rtol=2e-2)
    assert np.linalg.norm(x_eq) > 1.3 * np.linalg.norm(force / kx)
    print(
        f"|e_x| at rest: {np.linalg.norm(x_eq):.5f} m, force balance alone "
        f"{np.linalg.norm(force / kx):.5f} m"
    )

    # With integral action: below a millimetre.
    k = jnp.asarray(K_I)
    (_, (e_pid, code)), grad = run(k, sc)
    assert int(code) == 0
    assert np.linalg.norm(e_pid) < 1e-3 < np.linalg.norm(e_pd)
    if control_period is None:
        return

    # d cost / d (k_i, k_I) against central differences
    fd = np.zeros(2)
    for i in range(2):
        h = 1e-4 * float(k[i])
        e = jnp.zeros(2).at[i].set(h)
        up, down = value_and_grad(k + e, sc)[0][0], value_and_grad(k - e, sc)[0][0]
        fd[i] = (float(up) - float(down)) / (2 * h)
    print("gradient", np.asarray(grad), "central differences", fd)
    assert np.all(np.isfinite(np.asarray(grad))) and np.all(np.abs(fd) > 0)
    np.testing.assert_allclose(grad, fd, rtol=1e-5)


# ----------------------------------------------------------------------------
# Off by default: today's program
# ----------------------------------------------------------------------------


def frozen_control(gains, vehicle, t, x, v, R, Omega, reference):
    """A frozen copy of `quadrotor_control` as it was before integral action."""
    t = jnp.asarray(t, x.dtype)
    x_d, x1, x2, x3, x4 = _time_derivatives(lambda s: reference(s)[0], t, 4)
    b1d, b1d1, b1d2 = _time_derivatives(lambda s: reference(s)[1], t, 2)
    k_x, k_v = gains.k_x, gains.k_v
    m, g = vehicle.mass, vehicle.g
    e3 = _e3(x.dtype)
    Re3 = _mv(R, e3)
    Re3_1 = _mv(R, _cross(Omega, e3))
    e_x = x - x_d
    e_v = v - x1
    A = -k_x * e_x - k_v * e_v - m * g * e3 + m * x2
    f = -_dot(A, Re3)
    e_v1 = g * e3 - (f / m)[..., None] * Re3 - x2
    A1 = -k_x * e_v - k_v * e_v1 + m * x3
    f1 = -_dot(A1, Re3) - _dot(A, Re3_1)
    e_v2 = -(f1[..., None] * Re3 + f[..., None] * Re3_1) / m - x3
    A2 = -k_x * e_v1 - k_v * e_v2 + m * x4
    Rc, Rc1, Rc2 = _commanded_attitude(A, A1, A2, b1d, b1d1, b1d2)
    RcT = _mT(Rc)
    Omega_c = _vee(_mm(RcT, Rc1))
    dOmega_c = _vee(_mm(RcT, Rc2))
    M = _geometric_torque(gains, vehicle.body, R, Omega, Rc, Omega_c, dOmega_c)
    RtRc = _mm(_mT(R), Rc)
    e_R = _vee(_mT(RtRc))
    e_Omega = Omega - _mv(RtRc, Omega_c)
    Psi = 0.5 * (3.0 - jnp.trace(RtRc, axis1=-2, axis2=-1))
    return QuadrotorControl(f, M, Rc, Omega_c, dOmega_c, x_d, e_x, e_v, e_R, e_Omega, Psi)


class FrozenPlant(QuadrotorPlant):
    """A frozen copy of the drag-and-wind quadrotor (no rotors) as it was before integral
    action: a scene without integral gains must still compile to this program."""

    def control(self, t, y):
        R = y.R[..., 0, :, :]
        Omega, x, v = y.x[..., 0:3], y.x[..., 3:6], y.x[..., 6:9]
        return frozen_control(self.gains, self.vehicle, t, x, v, R, Omega, self.reference)

    def vector_field(self, t, y):
        R = y.R[..., 0, :, :]
        Omega, v = y.x[..., 0:3], y.x[..., 6:9]
        f, M = self.commanded(t, y)
        e3 = _e3(y.x.dtype)
        dOmega = self.vehicle.body.euler_rhs(Omega, M)
        dv = self.vehicle.g * e3 - (f / self.vehicle.mass)[..., None] * _mv(R, e3)
        dv = dv + self.drag_force(t, y) / self.vehicle.mass
        parts = [dOmega, v, dv]
        if self.sampled:
            parts.append(jnp.zeros_like(y.x[..., _N : _COUNTER + 1]))
        return LieTangent(Omega[..., None, :], jnp.concatenate(parts, -1))

    def for_step(self, dt, t0):
        if not self.sampled:
            return self
        n = jnp.maximum(jnp.round(self.control_period / dt), 1.0).astype(self.control_period.dtype)
        scene = eqx.tree_at(lambda s: s.steps_per_sample, self, n, is_leaf=lambda a: a is None)
        y = self.y0
        c = _sample_control(self, jnp.asarray(t0, y.x.dtype), y)
        at_sample = (y.x[..., _COUNTER] == 0)[..., None]
        held = jnp.where(at_sample, jnp.concatenate([c.f[..., None], c.M], -1), y.x[..., _HELD])
        x = jnp.concatenate([y.x[..., :_N], held, y.x[..., _COUNTER:]], -1)
        return eqx.tree_at(lambda s: s.y0, scene, LieState(y.R, x))

    def jump(self, t, y):
        if not self.sampled:
            return y
        count = y.x[..., _COUNTER] + 1.0
        sample = count > self.steps_per_sample - 0.5
        c = _control_of(self, t, y)
        new = jnp.concatenate([c.f[..., None], c.M], -1)
        held = jnp.where(sample[..., None], new, y.x[..., _HELD])
        count = jnp.where(sample, jnp.zeros_like(count), count)
        return LieState(y.R, jnp.concatenate([y.x[..., :_N], held, count[..., None]], -1))

    def observe(self, t, y):
        c = self.control(t, y)
        f, M = (y.x[..., 9], y.x[..., 10:13]) if self.sampled else (c.f, c.M)
        return {
            "R": y.R[..., 0, :, :],
            "Omega": y.x[..., 0:3],
            "M": M,
            "x": y.x[..., 3:6],
            "v": y.x[..., 6:9],
            "f": f,
            "Rc": c.Rc,
            "Omega_c": c.Omega_c,
            "dOmega_c": c.dOmega_c,
            "x_d": c.x_d,
            "e_x": c.e_x,
            "e_v": c.e_v,
            "e_R": c.e_R,
            "e_Omega": c.e_Omega,
            "Psi": c.Psi,
        }


@pytest.mark.parametrize("control_period", [None, 0.01])
def test_without_integral_gains_the_program_is_unchanged(control_period):
    sc = make_scene(control_period, k=(0.0, 0.0))  # the default: k_i = k_I = 0
    assert type(sc) is QuadrotorPlant and not sc.integral
    assert sc.gains.k_i is None and len(jax.tree.leaves(sc.gains)) == 4
    assert sc.y0.x.shape[-1] == (_COUNTER + 1 if control_period else _N)
    names = ("vehicle", "gains", "reference", "y0", "control_period", "drag", "wind")
    old = FrozenPlant(**{k: getattr(sc, k) for k in names})

    def f(sc):
        return s.simulate(sc, s.RKMK4(), 0.01, 4, save_every=2)

    # (JAX 0.10.0 prints the engine's batching rule with its address: a new closure per trace)
    new_jaxpr = re.sub(" at 0x[0-9a-f]+", "", str(jax.make_jaxpr(f)(sc)))
    old_jaxpr = re.sub(" at 0x[0-9a-f]+", "", str(jax.make_jaxpr(f)(old)))
    assert new_jaxpr == old_jaxpr.replace("FrozenPlant", "QuadrotorPlant")


# ----------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------


def test_bad_input():
    k = (16.0, 5.6, 8.81, 2.54)
    for name in ("k_i", "k_I", "c1", "c2"):
        with pytest.raises(ValueError, match=f"QuadrotorGains.{name} must be"):
            s.QuadrotorGains(*k, **{name: -1.0})
    for name in ("sigma_i", "sigma_I"):
        for bad in (0.0, -1.0, np.nan):
            with pytest.raises(ValueError, match=f"QuadrotorGains.{name} must be positive"):
                s.QuadrotorGains(*k, k_i=1.0, **{name: bad})
    with pytest.raises(ValueError, match="QuadrotorGains.k_i must be finite"):
        s.QuadrotorGains(*k, k_i=np.inf)
    with pytest.raises(ValueError, match="QuadrotorGains.c1 must be a scalar"):
        s.QuadrotorGains(*k, k_i=1.0, c1=[1.0, 2.0, 3.0])
    # An unclamped integral: sigma = inf; the gains still work positionally.
    g = s.QuadrotorGains(*k, 0.0, 0.3, sigma_i=np.inf)
    assert g.integral and float(g.k_I) == 0.3 and np.isinf(float(g.sigma_i))
    # Gains swapped into a scene built without (or with) integral action.
    plain, pid = make_scene(None, k=(0.0, 0.0)), make_scene(None)
    for scene, gains in ((plain, pid.gains), (pid, plain.gains)):
        swapped = eqx.tree_at(lambda q: q.gains, scene, gains)
        with pytest.raises(ValueError, match="integral action"):
            s.simulate(swapped, s.RKMK4(), 0.01, 2)
