"""Tracking scenes: the seed scenario, the near-pi start, unwinding, Dzhanibekov."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import simpson, solve_ivp
from scipy.spatial.transform import Rotation

import so3jax as s
from so3jax.plot import error_function

# ----------------------------------------------------------------------------
# An independent NumPy model of the seed scenario in R^9 x R^3 x R^9
# ----------------------------------------------------------------------------

J_SEED = np.diag([0.0820, 0.0845, 0.1377])
KR, KO = 8.81, 2.54


def np_hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def np_vee(W):
    return np.array([W[2, 1], W[0, 2], W[1, 0]])


def seed_reference(t):
    """The documented seed profile: 0.5 sin(2 pi 0.2 t + phi_i), phi = (0, 2 pi/3, 4 pi/3)."""
    w, phi = 2 * np.pi * 0.2, np.array([0.0, 2 * np.pi / 3, 4 * np.pi / 3])
    return 0.5 * np.sin(w * t + phi), 0.5 * w * np.cos(w * t + phi)


def seed_rhs(t, y):
    R, Om, Rd = y[:9].reshape(3, 3), y[9:12], y[12:].reshape(3, 3)
    Od, dOd = seed_reference(t)
    eR = 0.5 * np_vee(Rd.T @ R - R.T @ Rd)
    eO = Om - R.T @ Rd @ Od
    JO = J_SEED @ Om
    M = (
        -KR * eR
        - KO * eO
        + np.cross(Om, JO)
        - J_SEED @ (np_hat(Om) @ R.T @ Rd @ Od - R.T @ Rd @ dOd)
    )
    dOm = np.linalg.solve(J_SEED, M - np.cross(Om, JO))
    return np.concatenate([(R @ np_hat(Om)).ravel(), dOm, (Rd @ np_hat(Od)).ravel()])


def seed_R0():
    # scipy's intrinsic "ZYX" is Rz(phi) Ry(theta) Rx(psi).
    return Rotation.from_euler("ZYX", [np.pi / 3, -np.pi / 4, np.pi / 6]).as_matrix()


@pytest.fixture(scope="module")
def seed_traj():
    return s.simulate(s.scenes.seed(), s.RKMK4(), 1e-3, 10_000, save_every=10)


def test_seed_initial_state():
    sc = s.scenes.seed()
    R0 = seed_R0()
    np.testing.assert_allclose(sc.y0.R[0], R0, atol=1e-15)
    np.testing.assert_allclose(sc.y0.R[1], np.eye(3))
    np.testing.assert_allclose(sc.y0.x, np.zeros(3))
    np.testing.assert_allclose(sc.body.inertia, J_SEED)
    assert s.scenes.SEED_DURATION == 10.0
    psi0 = 0.5 * np.trace(np.eye(3) - R0)
    assert abs(psi0 - 0.9536) < 1e-4


def test_seed_closed_loop(seed_traj):
    tr = seed_traj
    assert bool(tr.status.ok)
    assert tr.Rd is not None and tr.M is not None
    assert tr.R.shape == (1001, 3, 3) and tr.M.shape == (1001, 3)
    psi = error_function(tr.R, tr.Rd)
    np.testing.assert_allclose(psi[0], 0.5 * np.trace(np.eye(3) - seed_R0()), rtol=1e-14)
    np.testing.assert_allclose(
        s.attitude_error_function(tr.R[::50], tr.Rd[::50]), psi[::50], atol=1e-12
    )
    t = np.asarray(tr.t)
    i5 = int(np.argmin(np.abs(t - 5.0)))
    assert psi[i5] < 1e-6
    # Psi alone need not decrease (the reference moves off at t = 0), but the Lyapunov
    # function V = 1/2 e_Omega . J e_Omega + k_R Psi does: V' = -k_Omega |e_Omega|^2.
    eO = np.asarray(tr.extras["e_Omega"])
    V = 0.5 * np.einsum("ni,ij,nj->n", eO, J_SEED, eO) + KR * psi
    assert np.all(np.diff(V) < 1e-12)
    dV = -KO * np.sum(eO**2, axis=-1)
    np.testing.assert_allclose(V[-1] - V[0], simpson(dV, x=t), rtol=1e-4)
    assert np.all(np.isfinite(tr.M))
    assert np.abs(np.asarray(tr.M)).max() < 20.0
    # the saved torque is the controller's at the saved state
    Od, dOd = s.SinusoidalRate()(tr.t[100])
    M = s.geometric_torque(
        s.GeometricGains(KR, KO), s.RigidBody(J_SEED), tr.R[100], tr.Omega[100], tr.Rd[100], Od, dOd
    )
    np.testing.assert_allclose(tr.M[100], M, atol=1e-13)
    # both rotations stay on the group without projection
    assert float(jnp.max(s.orthogonality_error(tr.R))) < 1e-11
    assert float(jnp.max(s.orthogonality_error(tr.Rd))) < 1e-11


def test_seed_matches_scipy_reference(seed_traj):
    y0 = np.concatenate([seed_R0().ravel(), np.zeros(3), np.eye(3).ravel()])
    sol = solve_ivp(seed_rhs, (0.0, 10.0), y0, method="DOP853", rtol=1e-12, atol=1e-12)
    assert sol.success
    yT = sol.y[:, -1]
    tr = seed_traj
    assert abs(float(tr.t[-1]) - 10.0) < 1e-12
    np.testing.assert_allclose(tr.R[-1], yT[:9].reshape(3, 3), atol=1e-8)
    np.testing.assert_allclose(tr.Omega[-1], yT[9:12], atol=1e-8)
    np.testing.assert_allclose(tr.Rd[-1], yT[12:].reshape(3, 3), atol=1e-8)


@pytest.mark.parametrize("method", [s.LieEuler(), s.CG3(), s.CF4(), s.LGVI(), s.RKMK45()])
def test_all_integrators_run_on_tracking(method, seed_traj):
    # 2 s at dt = 5e-3 against the RKMK4 run at dt = 1e-3.
    tr = s.simulate(s.scenes.seed(), method, 5e-3, 400, save_every=400)
    assert bool(tr.status.ok)
    i = int(np.argmin(np.abs(np.asarray(seed_traj.t) - 2.0)))
    err = float(jnp.max(jnp.abs(tr.R[-1] - seed_traj.R[i])))
    tol = {1: 5e-3, 2: 5e-4}.get(method.order, 1e-6)
    assert err < tol, (method.name, err)
    assert float(s.orthogonality_error(tr.Rd[-1])) < 1e-12


def test_grad_and_vmap_through_simulate_in_the_gains():
    """d Psi(T) / d k_R through `simulate`, against central differences; vmap over gains."""
    R0 = s.from_euler_zyx(jnp.pi / 3, -jnp.pi / 4, jnp.pi / 6)

    def final_psi(kR, method):
        sc = s.scenes.tracking(
            J_SEED, s.GeometricGains(kR, KO), R0, jnp.zeros(3), jnp.eye(3), s.SinusoidalRate()
        )
        tr = s.simulate(sc, method, 1e-2, 50, save_every=50)
        return s.attitude_error_function(tr.R[-1], tr.Rd[-1])

    h = 1e-5
    ks = jnp.array([KR - h, KR + h, KR, 20.0])
    # Forward mode with RKMK4 (one compilation for the batch: values and derivatives).
    f = jax.vmap(lambda k: jax.jvp(lambda k: final_psi(k, s.RKMK4()), (k,), (jnp.ones_like(k),)))
    values, derivs = jax.jit(f)(ks)
    np.testing.assert_allclose(derivs[2], (values[1] - values[0]) / (2 * h), rtol=1e-6)
    assert derivs[2] < 0 and values[3] < values[2]  # a stiffer attitude gain: a smaller error
    # vmap[i] == a single run: against the NumPy model (the first 0.5 s of the seed)
    y0 = np.concatenate([seed_R0().ravel(), np.zeros(3), np.eye(3).ravel()])
    sol = solve_ivp(seed_rhs, (0.0, 0.5), y0, method="DOP853", rtol=1e-12, atol=1e-12)
    R, Rd = sol.y[:9, -1].reshape(3, 3), sol.y[12:, -1].reshape(3, 3)
    np.testing.assert_allclose(values[2], 0.5 * np.trace(np.eye(3) - Rd.T @ R), rtol=1e-6)
    # Reverse mode (what a tuner uses), with LieEuler to keep the compilation short.
    g = jax.vmap(jax.value_and_grad(lambda k: final_psi(k, s.LieEuler())))
    values, grads = jax.jit(g)(ks[:3])
    np.testing.assert_allclose(grads[2], (values[1] - values[0]) / (2 * h), rtol=1e-6)


# ----------------------------------------------------------------------------
# Where things fail: near 180 degrees, unwinding
# ----------------------------------------------------------------------------


def test_near_pi_geometric_controller_is_slow_but_converges():
    sc = s.scenes.near_pi()
    np.testing.assert_allclose(
        sc.y0.R[0], Rotation.from_rotvec([0, 0, np.pi - 0.01]).as_matrix(), atol=1e-15
    )
    tr = s.simulate(sc, s.RKMK4(), 1e-3, 10_000, save_every=100)
    assert bool(tr.status.ok)
    psi = error_function(tr.R, tr.Rd)
    assert psi[0] > 1.9999
    assert psi[10] > 1.9  # after 1 s still within 0.1 of the maximum
    assert psi[-1] < 1e-6  # ... but it leaves: almost-global convergence
    # From the seed's start (Psi = 0.95) the same gains reach 1e-3 within 1 s.
    e_R0 = np.linalg.norm(np.asarray(tr.extras["e_R"][0]))
    np.testing.assert_allclose(e_R0, np.sin(np.pi - 0.01), rtol=1e-12)  # |e_R| = sin(angle)


def _travel(tr):
    """Total rotation angle travelled by the error Rd^T R (sum of small steps)."""
    E = jnp.einsum("nji,njk->nik", tr.Rd, tr.R)
    return float(jnp.sum(s.geodesic_distance(E[:-1], E[1:])))


@pytest.fixture(scope="module")
def unwinding_runs():
    out = {}
    for hyst in (False, True):
        tr = s.simulate(s.scenes.unwinding(hysteresis=hyst), s.RKMK4(), 1e-3, 4000, save_every=4)
        assert bool(tr.status.ok)
        out[hyst] = tr
    return out


def test_quaternion_controller_unwinds_without_hysteresis(unwinding_runs):
    tr = unwinding_runs[False]
    eta = np.asarray(tr.extras["q_lift"][:, 0])
    assert eta[0] > 0 and eta.min() < -0.2  # it crossed 180 degrees ...
    assert eta[-1] > 1 - 1e-9  # ... and was pulled back to q = +1: unwinding
    assert np.all(np.asarray(tr.extras["h"]) == 1.0)
    travel = _travel(tr)
    shortest = 2 * np.pi - s.scenes.UNWINDING_ANGLE  # keep going to the same attitude
    assert travel > np.pi + 1.0
    assert travel > shortest + 1.0
    assert error_function(tr.R[-1], tr.Rd[-1]) < 1e-8


def test_hysteresis_prevents_unwinding(unwinding_runs):
    tr = unwinding_runs[True]
    h = np.asarray(tr.extras["h"])
    eta = np.asarray(tr.extras["q_lift"][:, 0])
    assert h[0] == 1.0 and h[-1] == -1.0
    assert np.count_nonzero(np.diff(h)) == 1  # one jump, no chattering
    assert eta[-1] < -1 + 1e-9  # settles at q = -1: the same attitude, reached the short way
    travel = _travel(tr)
    shortest = 2 * np.pi - s.scenes.UNWINDING_ANGLE
    np.testing.assert_allclose(travel, shortest, rtol=1e-3)
    assert travel < _travel(unwinding_runs[False]) - 1.0
    assert error_function(tr.R[-1], tr.Rd[-1]) < 1e-8
    # the jump happened once h eta dropped below -delta
    k = int(np.argmax(h < 0))
    assert eta[k - 1] >= -0.2 - 1e-12 and eta[k] < -0.2 + 0.02


def test_memory_scenes_reject_lgvi():
    with pytest.raises(TypeError, match="LGVI needs"):
        s.simulate(s.scenes.unwinding(), s.LGVI(), 1e-3, 10)


# ----------------------------------------------------------------------------
# Dzhanibekov
# ----------------------------------------------------------------------------


def test_dzhanibekov_flips_periodically():
    sc = s.scenes.dzhanibekov()
    T, dt = 20.0, 2e-3
    tr = s.simulate(sc, s.RKMK4(), dt, int(T / dt), save_every=10)
    assert bool(tr.status.ok)
    Om = np.asarray(tr.Omega)
    J = np.array([1.0, 2.0, 3.0])

    def euler(t, w):
        return (np.roll(J, -1) - np.roll(J, -2)) * np.roll(w, -1) * np.roll(w, -2) / J

    sol = solve_ivp(
        euler, (0, T), np.asarray(sc.y0.x), method="DOP853", rtol=1e-12, atol=1e-12, t_eval=tr.t
    )
    np.testing.assert_allclose(Om, sol.y.T, atol=1e-5)
    signs = np.sign(Om[:, 1])
    flips = np.nonzero(signs[1:] != signs[:-1])[0]
    assert len(flips) >= 4  # it flips again and again
    gaps = np.diff(np.asarray(tr.t)[flips])
    np.testing.assert_allclose(gaps, gaps.mean(), rtol=0.02)  # ... periodically
    # energy and spatial angular momentum are conserved
    T_kin = 0.5 * np.sum(J * Om**2, axis=-1)
    pi = np.einsum("nij,nj->ni", np.asarray(tr.R), J * Om)
    assert np.abs(T_kin / T_kin[0] - 1).max() < 1e-8
    assert np.abs(pi - pi[0]).max() / np.linalg.norm(pi[0]) < 1e-8


# ----------------------------------------------------------------------------
# Construction and validation
# ----------------------------------------------------------------------------


def test_tracking_validation_and_dtype():
    I, z = jnp.eye(3), jnp.zeros(3)
    g = s.GeometricGains(1.0, 1.0)
    with pytest.raises(ValueError, match="Rd0 is not a rotation"):
        s.scenes.tracking(J_SEED, g, I, z, 2 * I)
    with pytest.raises(ValueError, match=r"Omega0 must have shape"):
        s.scenes.tracking(J_SEED, g, I, jnp.zeros(4), I)
    with pytest.raises(TypeError, match="gains must be a GeometricGains or a controller"):
        s.scenes.tracking(J_SEED, (1.0, 1.0), I, z, I)
    with pytest.raises(TypeError, match="reference must be a function"):
        s.scenes.tracking(J_SEED, g, I, z, I, reference=3.0)
    with pytest.raises(ValueError, match=r"reference\(t\) must return"):
        s.scenes.tracking(J_SEED, g, I, z, I, reference=lambda t: jnp.zeros(3))
    with pytest.raises(ValueError, match="J1 < J2 < J3"):
        s.scenes.dzhanibekov(inertia=(2.0, 1.0, 3.0))
    # any function t -> (w, dw) is a reference; the dtype follows R0
    sc = s.scenes.tracking(
        jnp.ones(3, jnp.float64),
        g,
        jnp.eye(3, dtype=jnp.float32),
        z,
        I,
        reference=lambda t: (jnp.sin(t) * jnp.ones(3), jnp.cos(t) * jnp.ones(3)),
    )
    leaves = [x for x in jax.tree.leaves(sc) if eqx.is_inexact_array(x)]
    assert all(x.dtype == jnp.float32 for x in leaves)
    tr = s.simulate(sc, s.RKMK4(), 1e-2, 20)
    assert tr.R.dtype == jnp.float32 and bool(tr.status.ok)
    # Rd follows the reference: Rd' = Rd hat(w(t)) with w(t) = sin(t)(1, 1, 1), a fixed axis,
    # so Rd(t) = exp((1 - cos t)(1, 1, 1)).
    Rd_exact = Rotation.from_rotvec((1 - math.cos(0.2)) * np.ones(3)).as_matrix()
    np.testing.assert_allclose(tr.Rd[-1], Rd_exact, atol=2e-6)
