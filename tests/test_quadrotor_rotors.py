"""The quadrotor's rotors (allocation, clipping, lag), drag and wind against SciPy.

The reference below is independent of so3jax: Lee's controller from the paper's
formulas with hand-written chain rules (as in ``tests/quadrotor_reference.py`` and
``tests/test_quadrotor.py``), the allocation ``A`` of Lee, Leok & McClamroch (CDC
2010) eq. (1) inverted by `numpy.linalg.solve`, and the plant integrated by SciPy's
DOP853 hold by hold.
"""

import dataclasses
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import so3jax as s
from so3jax import scenes
from so3jax._quadrotor import (
    _COUNTER,
    _HELD,
    _N,
    DIFFTUNE_GAINS,
    DIFFTUNE_INERTIA,
    DIFFTUNE_MASS,
    Quadrotor,
    _control_of,
    _e3,
)
from so3jax._so3 import _mv
from so3jax._state import LieState, LieTangent

M_, J_ = DIFFTUNE_MASS, np.diag(DIFFTUNE_INERTIA)
GAINS = np.asarray(DIFFTUNE_GAINS)  # k_x, k_v, k_R, k_Omega
G = 9.81
E1, E3 = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
X_D = np.array([0.3, -0.2, -0.1])  # hover point
ARM, C_TF = 0.315, 0.02
T, PER, N_HOLDS = 0.01, 16, 120  # hold 10 ms, 16 RKMK4 steps per hold, 1.2 s


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


def np_control(x, v, R, W, k):
    """Lee's controller (CDC 2010, eqs. (12)-(16)) hovering at ``X_D`` with ``b1_d = e1``.

    Its nominal model: ``e_v' = g e3 - f R e3 / m`` (no limits, lag, drag or wind).
    """
    kx, kv, kR, kW = k
    A = -kx * (x - X_D) - kv * v - M_ * G * E3
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
    return f, M


class NumpyPlant:
    """Rotors (eq. (1), clipped, lagged), linear drag in a wind ``w(t)``; SciPy DOP853."""

    def __init__(self, thrust_min, thrust_max, tau, drag, wind):
        d, c = ARM, C_TF
        self.A = np.array([[1, 1, 1, 1], [0, -d, 0, d], [d, 0, -d, 0], [-c, c, -c, c]], float)
        self.lo, self.hi, self.tau = thrust_min, thrust_max, tau
        self.D = np.diag(drag)
        self.wind = wind if callable(wind) else (lambda t: np.asarray(wind, float))

    def rotor_command(self, f, M):
        return np.clip(np.linalg.solve(self.A, np.r_[f, M]), self.lo, self.hi)

    def rates(self, t, x, v, R, W, F):
        """``(dv, dW)`` under the rotor thrusts ``F``."""
        fM = self.A @ F
        f, M = fM[0], fM[1:]
        dv = G * E3 - f / M_ * (R @ E3) - R @ self.D @ R.T @ (v - self.wind(t)) / M_
        return dv, np.linalg.solve(J_, M - np.cross(W, J_ @ W))

    def rhs(self, t, y, cmd):
        x, v, R, W, F = y[0:3], y[3:6], y[6:15].reshape(3, 3), y[15:18], y[18:22]
        dv, dW = self.rates(t, x, v, R, W, F)
        return np.concatenate([v, dv, (R @ np_hat(W)).ravel(), dW, (cmd - F) / self.tau])

    def run(self, x0, v0, R0, W0, k, n_holds):
        """States at ``t = 0, T, ..., n_holds T`` and the commands sampled at each hold."""
        y = np.concatenate([x0, v0, R0.ravel(), W0, np.zeros(4)])
        ys, cmds = [], []
        for i in range(n_holds + 1):
            f, M = np_control(y[0:3], y[3:6], y[6:15].reshape(3, 3), y[15:18], k)
            cmd = self.rotor_command(f, M)
            if i == 0:
                y[18:22] = cmd  # the thrusts start at the clipped command at t = 0
            ys.append(y.copy())
            cmds.append(np.r_[f, M])
            if i == n_holds:
                break
            sol = solve_ivp(
                self.rhs, (i * T, (i + 1) * T), y, "DOP853", rtol=1e-12, atol=1e-12, args=(cmd,)
            )
            y = sol.y[:, -1]
        return np.asarray(ys), np.asarray(cmds)


X0, V0, W0 = np.zeros(3), np.array([0.2, 0.0, -0.1]), np.array([0.5, -0.3, 0.2])
AXIS = np.array([1.0, 0.3, 0.0]) / np.sqrt(1.09)
DRAG, WIND = np.array([0.3, 0.4, 0.6]), np.array([2.0, -1.0, 0.5])


def make_scene(gains=GAINS, R0=None, control_period=T, **options):
    R0 = np.asarray(s.from_axis_angle(AXIS, 1.5)) if R0 is None else R0
    return scenes.quadrotor(
        M_,
        DIFFTUNE_INERTIA,
        s.QuadrotorGains(*gains),
        s.HoverReference(X_D),
        x0=X0,
        v0=V0,
        R0=R0,
        Omega0=W0,
        control_period=control_period,
        **options,
    )


@eqx.filter_jit
def run(scene, n_holds):
    return s.simulate(scene, s.RKMK4(), T / PER, PER * n_holds, save_every=PER)


# ----------------------------------------------------------------------------
# Against SciPy
# ----------------------------------------------------------------------------


def test_rotors_lag_drag_wind_match_scipy_dop853():
    # A recovery from 86 degrees of tilt: rotor commands above thrust_max (or below 0)
    # from the start and on and off for most of the first second, within the limits
    # over the last 0.3 s.
    lo, hi, tau, n_holds = 0.0, 18.0, 0.03, N_HOLDS
    rotors = s.Rotors(ARM, C_TF, lo, hi, time_constant=tau)
    sc = make_scene(rotors=rotors, drag=DRAG, wind=WIND)
    tr = run(sc, n_holds)
    assert bool(tr.status.ok)
    R0 = np.asarray(sc.y0.R[0])
    ref = NumpyPlant(lo, hi, tau, DRAG, WIND)
    ys, cmds = ref.run(X0, V0, R0, W0, GAINS, n_holds)

    ex = {k: np.asarray(v) for k, v in tr.extras.items()}
    alloc = np.linalg.solve(ref.A, cmds.T).T
    saturated = ((alloc < lo) | (alloc > hi)).any(1)
    assert saturated[:5].all() and not saturated[-30:].any()
    # the controller's command at each sample, and the rotor thrusts' algebra
    np.testing.assert_allclose(ex["f_cmd"], cmds[:, 0], rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(ex["M_cmd"], cmds[:, 1:], rtol=1e-8, atol=1e-8)
    fM = ex["rotor_thrust"] @ ref.A.T
    np.testing.assert_allclose(ex["f"], fM[:, 0], rtol=1e-13)
    np.testing.assert_allclose(np.asarray(tr.M), fM[:, 1:], atol=1e-13 * np.abs(fM).max())
    # the trajectory, rotor thrusts included
    err = max(
        np.abs(ex["x"] - ys[:, 0:3]).max(),
        np.abs(ex["v"] - ys[:, 3:6]).max(),
        np.abs(np.asarray(tr.R).reshape(-1, 9) - ys[:, 6:15]).max(),
        np.abs(np.asarray(tr.Omega) - ys[:, 15:18]).max(),
        np.abs(ex["rotor_thrust"] - ys[:, 18:22]).max() / hi,
    )
    print(f"max error against DOP853 over {n_holds} holds: {err:.2e}")
    assert err < 1e-8


def test_allocation_and_its_inverse():
    rotors = s.Rotors(ARM, C_TF, 0.0, 18.0)
    A = np.array([[1, 1, 1, 1], [0, -ARM, 0, ARM], [ARM, 0, -ARM, 0], [-C_TF, C_TF, -C_TF, C_TF]])
    np.testing.assert_allclose(rotors.matrix(), A, rtol=1e-15)
    fM = np.random.default_rng(0).normal(size=(5, 4)) * [40.0, 2.0, 2.0, 0.2]
    thrusts = np.asarray(rotors.allocate(fM[:, 0], fM[:, 1:]))
    np.testing.assert_allclose(thrusts, np.linalg.solve(A, fM.T).T, rtol=1e-13, atol=1e-13)
    f, M = rotors.wrench(thrusts)
    np.testing.assert_allclose(np.c_[f, M], fM, rtol=1e-13, atol=1e-13)
    np.testing.assert_array_equal(rotors.command(fM[:, 0], fM[:, 1:]), np.clip(thrusts, 0, 18))


@pytest.mark.parametrize("tau", [0.03, None])
def test_continuous_control_vector_field_matches_numpy(tau):
    # Continuous control, a wind that varies in time; a state where rotors 3 and 4
    # are commanded past their limits.
    def wind(t):
        return jnp.stack([jnp.sin(t), jnp.cos(t), 0.1 * t])

    rotors = s.Rotors(ARM, C_TF, 0.0, 18.0, time_constant=tau)
    sc = make_scene(control_period=None, rotors=rotors, drag=DRAG, wind=wind)
    ref = NumpyPlant(0.0, 18.0, tau, DRAG, lambda t: np.array([np.sin(t), np.cos(t), 0.1 * t]))
    R0 = np.asarray(sc.y0.R[0])
    cmd0 = ref.rotor_command(*np_control(X0, V0, R0, W0, GAINS))
    if tau is not None:  # the thrusts start at the clipped command
        np.testing.assert_allclose(sc.y0.x[9:13], cmd0, rtol=1e-12)

    rng = np.random.default_rng(2)
    x, v, W = rng.normal(size=(3, 3))
    R = np.asarray(s.from_axis_angle(np.array([0.0, 1.0, 0.0]), 0.3))
    F = rng.uniform(0.0, 18.0, 4)
    t = 0.7
    cmd = ref.rotor_command(*np_control(x, v, R, W, GAINS))
    assert cmd[2] == 18.0 and cmd[3] == 0.0 and 0 < cmd[0] < 18 and 0 < cmd[1] < 18
    state = np.r_[W, x, v] if tau is None else np.r_[W, x, v, F]
    out = eqx.filter_jit(lambda sc, y: sc.vector_field(jnp.asarray(t), y))(
        sc, LieState(jnp.asarray(R[None]), jnp.asarray(state))
    )
    dv, dW = ref.rates(t, x, v, R, W, cmd if tau is None else F)
    want = np.r_[dW, v, dv] if tau is None else np.r_[dW, v, dv, (cmd - F) / tau]
    np.testing.assert_allclose(out.xi[0], W, rtol=1e-15)
    np.testing.assert_allclose(out.dx, want, rtol=1e-11, atol=1e-11 * np.abs(want).max())


# ----------------------------------------------------------------------------
# Without the options: today's scene, bit for bit
# ----------------------------------------------------------------------------


class NominalQuadrotor(Quadrotor):
    """A frozen copy of the quadrotor's vector field, jump and observe as they were
    before rotors, drag and wind: the nominal scene must still compile to this program."""

    def vector_field(self, t, y):
        R = y.R[..., 0, :, :]
        Omega, v = y.x[..., 0:3], y.x[..., 6:9]
        if self.sampled:
            f, M = y.x[..., 9], y.x[..., 10:13]
        else:
            c = self.control(t, y)
            f, M = c.f, c.M
        e3 = _e3(y.x.dtype)
        dOmega = self.vehicle.body.euler_rhs(Omega, M)
        dv = self.vehicle.g * e3 - (f / self.vehicle.mass)[..., None] * _mv(R, e3)
        parts = [dOmega, v, dv]
        if self.sampled:
            parts.append(jnp.zeros_like(y.x[..., _N:]))
        return LieTangent(Omega[..., None, :], jnp.concatenate(parts, -1))

    def jump(self, t, y):
        if not self.sampled:
            return y
        count = y.x[..., _COUNTER] + 1.0
        sample = count > self.steps_per_sample - 0.5
        c = _control_of(self, t, y)
        new = jnp.concatenate([c.f[..., None], c.M], -1)
        held = jnp.where(sample[..., None], new, y.x[..., _HELD])
        count = jnp.where(sample, jnp.zeros_like(count), count)
        x = jnp.concatenate([y.x[..., :_N], held, count[..., None]], -1)
        return LieState(y.R, x)

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


def _nominal_copy(sc):
    names = ("vehicle", "gains", "reference", "y0", "control_period")
    return NominalQuadrotor(**{k: getattr(sc, k) for k in names})


@pytest.mark.parametrize("control_period", [0.01, None])
def test_without_options_the_program_is_unchanged(control_period):
    sc = scenes.quadrotor_recovery(control_period)
    old = _nominal_copy(sc)
    assert type(sc) is Quadrotor  # no rotors, drag or wind among its fields
    fields = {"vehicle", "gains", "reference", "y0", "control_period", "steps_per_sample"}
    assert {f.name for f in dataclasses.fields(sc)} == fields

    def f(sc):
        return s.simulate(sc, s.RKMK4(), 0.005, 8, save_every=4)

    # (JAX 0.10.0 prints the engine's batching rule with its address: a new closure per trace)
    new_jaxpr = re.sub(" at 0x[0-9a-f]+", "", str(jax.make_jaxpr(f)(sc)))
    old_jaxpr = re.sub(" at 0x[0-9a-f]+", "", str(jax.make_jaxpr(f)(old)))
    assert new_jaxpr == old_jaxpr.replace("NominalQuadrotor", "Quadrotor")
    if control_period is not None:
        a, b = f(sc), f(old)
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
            np.testing.assert_array_equal(x, y)


# ----------------------------------------------------------------------------
# Gradients through the rotor model
# ----------------------------------------------------------------------------


def _loss(k, scene):
    sc = eqx.tree_at(lambda q: q.gains, scene, s.QuadrotorGains(k[0], k[1], k[2], k[3]))
    tr = s.simulate(sc, s.RKMK4(), T / 2, 2 * 60, save_every=2)
    rotor_cmd = sc.rotors.allocate(tr.extras["f_cmd"], tr.extras["M_cmd"])
    return jnp.sum(tr.extras["e_x"] ** 2) + 1e-3 * jnp.sum(tr.extras["e_R"] ** 2), rotor_cmd


@eqx.filter_jit
def _value_and_grad(k, scene):
    """``((loss, rotor commands), d loss / d k)`` by forward mode (one tangent per gain)."""

    def one(direction):
        return jax.jvp(lambda k: _loss(k, scene), (k,), (direction,), has_aux=True)

    value, tangent, aux = jax.vmap(one)(jnp.eye(k.shape[0], dtype=k.dtype))
    return (value[0], aux[0]), tangent


def test_gradient_in_the_gains_through_rotors():
    k = jnp.asarray(GAINS)
    # Small tilt, wide limits: no rotor saturates, the loss is smooth in the gains.
    wide = s.Rotors(ARM, C_TF, -100.0, 100.0, time_constant=0.03)
    sc = make_scene(R0=np.asarray(s.from_axis_angle(AXIS, 0.3)), rotors=wide, drag=DRAG, wind=WIND)
    (value, cmd), grad = _value_and_grad(k, sc)
    assert np.all((np.asarray(cmd) > -100.0) & (np.asarray(cmd) < 100.0))
    # The thrusts start at the command of the swapped gains (`Quadrotor.for_step`).
    k2 = k * 1.1
    tr_swapped = run(eqx.tree_at(lambda q: q.gains, sc, s.QuadrotorGains(*k2)), N_HOLDS)
    tr_built = run(
        make_scene(k2, R0=np.asarray(sc.y0.R[0]), rotors=wide, drag=DRAG, wind=WIND), N_HOLDS
    )
    for x, y in zip(jax.tree.leaves(tr_swapped), jax.tree.leaves(tr_built), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-13, atol=1e-13)

    fd = np.zeros(4)
    for i in range(4):
        h = 1e-5 * float(k[i])
        e = jnp.zeros(4).at[i].set(h)
        up, down = _value_and_grad(k + e, sc)[0][0], _value_and_grad(k - e, sc)[0][0]
        fd[i] = (float(up) - float(down)) / (2 * h)
    print("gradient", np.asarray(grad), "central differences", fd)
    assert np.all(np.abs(fd) > 1e-6 * np.abs(fd).max())
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())

    # Large tilt, thrust_max low: rotors saturate; the gradient is still finite.
    tight = s.Rotors(ARM, C_TF, 0.0, 18.0, time_constant=0.03)
    sc = make_scene(rotors=tight, drag=DRAG, wind=WIND)
    (value, cmd), grad = _value_and_grad(k, sc)
    assert np.any(np.asarray(cmd) > 18.0) and np.any(np.asarray(cmd) < 0.0)
    assert np.isfinite(float(value)) and np.all(np.isfinite(np.asarray(grad)))


# ----------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------


def test_bad_input():
    rotors = s.Rotors(ARM, C_TF, 0.0, 18.0)
    with pytest.raises(ValueError, match="arm must be positive"):
        s.Rotors(0.0, C_TF)
    with pytest.raises(ValueError, match="arm must be a scalar"):
        s.Rotors([0.3, 0.3], C_TF)
    with pytest.raises(ValueError, match="torque_coefficient must be positive"):
        s.Rotors(ARM, -0.01)
    with pytest.raises(ValueError, match=r"thrust_min \(5.0\) must be less than thrust_max"):
        s.Rotors(ARM, C_TF, 5.0, 5.0)
    with pytest.raises(ValueError, match="thrust_min must be finite"):
        s.Rotors(ARM, C_TF, -np.inf)
    for tau in (0.0, -0.1, np.nan):
        with pytest.raises(ValueError, match="time_constant must be positive"):
            s.Rotors(ARM, C_TF, time_constant=tau)
    with pytest.raises(ValueError, match="time_constant must be a scalar"):
        s.Rotors(ARM, C_TF, time_constant=np.ones(4))
    with pytest.raises(ValueError, match=r"rotors.thrust_max \(10 N\) cannot hover"):
        make_scene(rotors=s.Rotors(ARM, C_TF, 0.0, 10.0))  # 4 x 10 N < 4.34 x 9.81 N
    with pytest.raises(TypeError, match="rotors must be a so3jax.Rotors"):
        make_scene(rotors=(ARM, C_TF))
    with pytest.raises(ValueError, match="drag must be >= 0"):
        make_scene(drag=(0.1, -0.1, 0.1))
    with pytest.raises(ValueError, match="drag must be a 3-vector"):
        make_scene(rotors=rotors, drag=np.ones(2))
    with pytest.raises(ValueError, match="wind must be a 3-vector"):
        make_scene(drag=DRAG, wind=np.ones((2, 3)))
    with pytest.raises(ValueError, match=r"wind\(t\) must return shape \(3,\)"):
        make_scene(drag=DRAG, wind=lambda t: jnp.ones(2) * t)
    with pytest.raises(ValueError, match="wind acts through the drag"):
        make_scene(wind=WIND)
