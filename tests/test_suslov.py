"""Suslov's nonholonomic rigid body (`so3jax.scenes.suslov`).

The reference is written here independently, in NumPy: the constrained
equations as the linear (KKT) system

    [ J   -a ] [Omega'] = [(J Omega) x Omega]
    [ a^T  0 ] [lambda]   [        0        ]

solved at every evaluation and integrated by SciPy's DOP853 in R^9 x R^3.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from exact_rigid_body import hat
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

import so3jax
from so3jax._integrators import METHODS

MOMENTS = np.array([1.0, 2.0, 3.0])
A = np.array([1.0, 0.6, 0.3])  # not an eigenvector of J: the generic case
R0 = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
T, DT, SAVE = 10.0, 0.01, 50  # 1000 steps, 21 saved points


def start(J, a, angle=0.3, speed=1.5):
    """``Omega0`` on the constraint plane, ``angle`` away from the repelling rotation.

    Steady rotations of Suslov's body span ``a^perp ∩ (J a)^perp``; from near
    ``-Omega*`` the body turns over to ``+Omega*`` within the run.
    """
    a = a / np.linalg.norm(a)
    w = np.cross(a, J @ a)
    w /= np.linalg.norm(w)
    return speed * (-np.cos(angle) * w + np.sin(angle) * np.cross(a, w))


J_DIAG = np.diag(MOMENTS)
OMEGA0 = start(J_DIAG, A)


def scene(dtype=jnp.float64, inertia=MOMENTS, Omega0=OMEGA0):
    return so3jax.scenes.suslov(
        jnp.asarray(inertia, dtype), jnp.asarray(A, dtype), jnp.asarray(R0, dtype), Omega0
    )


def ambient_suslov(J, a, R0, Omega0, t_eval, rtol=1e-12, atol=1e-12):
    """DOP853 on ``R' = R hat(Omega)`` and the KKT system above, restarted at each output."""
    J, a = np.asarray(J, float), np.asarray(a, float)
    K = np.zeros((4, 4))
    K[:3, :3], K[:3, 3], K[3, :3] = J, -a, a

    def f(t, y):
        R, W = y[:9].reshape(3, 3), y[9:]
        rhs = np.concatenate([np.cross(J @ W, W), [0.0]])
        dW = np.linalg.solve(K, rhs)[:3]
        return np.concatenate([(R @ hat(W)).ravel(), dW])

    y = np.concatenate([np.asarray(R0, float).ravel(), np.asarray(Omega0, float)])
    out = [y]
    for ta, tb in zip(t_eval[:-1], t_eval[1:], strict=True):
        sol = solve_ivp(f, (ta, tb), y, method="DOP853", rtol=rtol, atol=atol)
        assert sol.success, sol.message
        y = sol.y[:, -1]
        out.append(y)
    out = np.array(out)
    return out[:, :9].reshape(-1, 3, 3), out[:, 9:]


@pytest.fixture(scope="module")
def reference():
    t = np.linspace(0.0, T, round(T / DT) // SAVE + 1)
    return ambient_suslov(J_DIAG, A, R0, OMEGA0, t)


@pytest.fixture(scope="module")
def trajectory():
    """RKMK45 through `simulate`: 1000 steps, 21 saved points."""
    sc = scene()
    return sc, so3jax.simulate(sc, so3jax.RKMK45(), DT, round(T / DT), save_every=SAVE)


def _run(scene, method, t1, n):
    """``n`` steps to ``t1``: the final state, ``max_k |E_k - E_0|`` and ``max_k |<Omega_k, a>|``.

    ``t1`` and ``n`` go in as arrays (`filter_jit` takes Python numbers as static):
    one compilation per method for every step size.
    """
    return _run_jit(scene, method, jnp.asarray(t1, scene.y0.R.dtype), jnp.asarray(n))


@eqx.filter_jit
def _run_jit(scene, method, t1, n):
    dt = t1 / n
    E0 = scene.body.kinetic_energy(scene.y0.x)

    def body(k, carry):
        y, dE, res = carry
        y = method.step(scene, k * dt, y, dt)[0]
        dE = jnp.maximum(dE, jnp.abs(scene.body.kinetic_energy(y.x) - E0))
        return y, dE, jnp.maximum(res, jnp.abs(scene.constraint(y.x)))

    zero = jnp.zeros_like(E0)
    return jax.lax.fori_loop(0, n, body, (scene.y0, zero, zero))


def _constraint(sc, Omega):
    return np.abs(np.asarray(Omega) @ np.asarray(sc.a))


# --------------------------------------------------------------------------
# The scene
# --------------------------------------------------------------------------


def test_scene_fields_and_vector_field():
    sc = scene()
    a_hat = A / np.linalg.norm(A)
    np.testing.assert_allclose(sc.a, a_hat, rtol=1e-15)
    np.testing.assert_allclose(sc.y0.x, OMEGA0, atol=1e-15)
    assert sc.y0.R.shape == (1, 3, 3)

    @jax.jit
    def evaluate(W):
        y = so3jax.LieState(jnp.broadcast_to(sc.y0.R, W.shape[:1] + (1, 3, 3)), W)
        f = sc.vector_field(0.0, y)
        _, dE = jax.jvp(sc.body.kinetic_energy, (W,), (f.dx,))
        _, dC = jax.jvp(sc.body.casimir, (W,), (f.dx,))
        return f, sc.multiplier(W), dE, dC

    # <Omega', a> = 0 for any Omega (on the plane or not); lambda as in the KKT system.
    rng = np.random.default_rng(0)
    W = rng.normal(size=(5, 3))
    f, lams, _, _ = evaluate(jnp.asarray(W))
    np.testing.assert_allclose(np.asarray(f.dx) @ a_hat, 0.0, atol=1e-14)
    np.testing.assert_allclose(f.xi[:, 0], W, rtol=0, atol=0)
    K = np.zeros((4, 4))
    K[:3, :3], K[:3, 3], K[3, :3] = J_DIAG, -a_hat, a_hat
    for Wi, dWi, lam in zip(W, f.dx, lams, strict=True):
        sol = np.linalg.solve(K, np.concatenate([np.cross(J_DIAG @ Wi, Wi), [0.0]]))
        np.testing.assert_allclose(dWi, sol[:3], rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(lam, sol[3], rtol=1e-12, atol=1e-14)
    # On the plane the constraint torque does no work: dE/dt = 0, but d|J Omega|/dt != 0.
    _, _, dE, dC = evaluate(so3jax.scenes.suslov_project(A, W))
    np.testing.assert_allclose(dE, 0.0, atol=1e-13)
    assert np.abs(np.asarray(dC)).max() > 0.1


def test_project_helper():
    rng = np.random.default_rng(1)
    W = rng.normal(size=(4, 3))
    P = np.asarray(so3jax.scenes.suslov_project(3.0 * A, W))
    np.testing.assert_allclose(P @ A, 0.0, atol=1e-14)
    a_hat = A / np.linalg.norm(A)
    np.testing.assert_allclose(P, W - np.outer(W @ a_hat, a_hat), atol=1e-15)


def test_dtype_follows_R0_and_full_inertia():
    sc = scene(jnp.float32)
    assert sc.y0.R.dtype == sc.y0.x.dtype == sc.a.dtype == sc.body.inertia.dtype == jnp.float32
    Q = Rotation.from_rotvec([0.2, 0.5, -0.4]).as_matrix()
    sc = so3jax.scenes.suslov(Q @ J_DIAG @ Q.T, A, R0, start(Q @ J_DIAG @ Q.T, A))
    assert sc.body.inertia.shape == (3, 3)


def test_under_jit_and_vmap():
    # Traced arguments skip the eager value checks; the scene still builds and runs.
    def final_omega(W0):
        sc = so3jax.scenes.suslov(MOMENTS, A, R0, W0)
        return so3jax.simulate(sc, so3jax.LieEuler(), DT, 200, save_every=200).Omega[-1]

    out = jax.jit(jax.vmap(final_omega))(jnp.stack([OMEGA0, -OMEGA0]))
    y, _, _ = _run(scene(), so3jax.LieEuler(), 200 * DT, 200)
    np.testing.assert_allclose(out[0], y.x, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(np.asarray(out) @ A, 0.0, atol=1e-13)


# --------------------------------------------------------------------------
# Against SciPy, and the constraint for every method
# --------------------------------------------------------------------------


def test_matches_ambient_dop853(trajectory, reference):
    sc, tr = trajectory
    R_ref, W_ref = reference
    err_R = np.abs(np.asarray(tr.R) - R_ref).max()
    err_W = np.abs(np.asarray(tr.Omega) - W_ref).max()
    print(f"RKMK45: max |R - R_ref| = {err_R:.1e}, max |Omega - Omega_ref| = {err_W:.1e}")
    assert err_R < 1e-8 and err_W < 1e-8
    # The body turns over from near -Omega* to near +Omega*: a real test, not a rest state.
    w = np.cross(A, J_DIAG @ A)
    assert W_ref[0] @ w < -1.0 and W_ref[-1] @ w > 1.0


@pytest.mark.parametrize("name", ["RKMK4", "CF4", "RKMK4-cayley"])
def test_final_state_matches_ambient_dop853(name, reference):
    y, _, _ = _run(scene(), METHODS[name](), T, round(T / DT))
    R_ref, W_ref = reference
    err = max(np.abs(np.asarray(y.R[0]) - R_ref[-1]).max(), np.abs(y.x - W_ref[-1]).max())
    print(f"{name}: error at t = {T:g}: {err:.1e}")
    assert err < 1e-8


def test_full_inertia_matches_ambient_dop853():
    Q = Rotation.from_rotvec([0.2, 0.5, -0.4]).as_matrix()
    J = Q @ J_DIAG @ Q.T
    W0 = start(J, A, angle=0.6)
    sc = so3jax.scenes.suslov(J, A, R0, W0)
    # Same shapes and steps as `trajectory`: its compiled run is reused.
    tr = so3jax.simulate(sc, so3jax.RKMK45(), DT, round(T / DT), save_every=SAVE)
    R_ref, W_ref = ambient_suslov(J, A, R0, W0, np.asarray(tr.t))
    err = max(np.abs(np.asarray(tr.R) - R_ref).max(), np.abs(np.asarray(tr.Omega) - W_ref).max())
    print(f"RKMK45, full inertia: max error {err:.1e}")
    assert err < 1e-8
    assert _constraint(sc, tr.Omega).max() <= 1e-12


def test_adaptive_tsit5_matches_ambient_dop853(reference):
    sc = scene()
    tr = so3jax.simulate(sc, so3jax.RKMKTsit5(), t1=T, rtol=1e-11, atol=1e-11, saveat=21)
    assert bool(tr.status.ok)
    R_ref, W_ref = reference
    err = max(np.abs(np.asarray(tr.R) - R_ref).max(), np.abs(np.asarray(tr.Omega) - W_ref).max())
    print(f"RKMKTsit5: max error {err:.2e}")
    assert err < 1e-8
    assert _constraint(sc, tr.Omega).max() <= 1e-12


@pytest.mark.parametrize("name", [n for n in METHODS if n != "LGVI"])
def test_runge_kutta_methods_keep_the_constraint(name):
    """``|<Omega, a>| <= 1e-12`` at every one of 1000 steps (``_run`` tracks the maximum)."""
    sc = scene()
    y, _, res = _run(sc, METHODS[name](), T, round(T / DT))
    print(f"{name}: max |<Omega, a>| = {float(res):.1e}")
    assert float(res) <= 1e-12
    assert float(so3jax.orthogonality_error(y.R).max()) < 1e-13


def test_saved_steps_keep_the_constraint(trajectory):
    sc, tr = trajectory
    assert bool(tr.status.ok)
    assert _constraint(sc, tr.Omega).max() <= 1e-12


def test_lgvi_converges_but_drifts_off_the_constraint(reference):
    """LGVI takes ``lambda a`` as an external torque: ``<Omega, a>`` drifts like dt^2.

    Its fixed-point iteration for the Omega-dependent torque has converged (more
    iterations change a step far below its error), and the method converges
    with order 2.
    """
    sc = scene()
    _, W_ref = reference
    (y1, _, r1), (y2, _, r2) = (_run(sc, so3jax.LGVI(), T, n) for n in (1000, 2000))
    e1, e2 = (float(jnp.abs(y.x - W_ref[-1]).max()) for y in (y1, y2))
    # One step, eagerly: 3 (the default) against 10 fixed-point iterations.
    y_mid = so3jax.LieState(sc.y0.R, jnp.asarray(W_ref[10]))
    step3, step10 = (
        jax.jit(lambda y, m=m: m.step(sc, 0.0, y, DT)[0].x)(y_mid)
        for m in (so3jax.LGVI(), so3jax.LGVI(torque_iters=10))
    )
    iters = float(jnp.abs(step3 - step10).max())
    print(
        f"LGVI: error {e1:.1e} -> {e2:.1e}, |<Omega, a>| {float(r1):.1e} -> {float(r2):.1e} "
        f"at dt/2; one step, 3 against 10 torque iterations: {iters:.1e}"
    )
    assert iters < 1e-13
    assert 3.5 < e1 / e2 < 4.5
    assert 3.5 < r1 / r2 < 4.5
    assert r1 > 1e-6  # honestly off the constraint, by much more than round-off


@pytest.mark.parametrize("name", ["RKMK4"])
def test_float32_keeps_the_constraint(name):
    sc = scene(jnp.float32)
    n = 500
    tr = so3jax.simulate(sc, METHODS[name](), 0.02, n, save_every=10)
    assert tr.Omega.dtype == jnp.float32 and bool(tr.status.ok)
    res = _constraint(sc, tr.Omega)
    bound = 10 * np.finfo(np.float32).eps * np.sqrt(n) * np.linalg.norm(OMEGA0)
    print(f"{name} float32: max |<Omega, a>| = {res.max():.1e} (bound {bound:.1e})")
    assert res.max() <= bound


# --------------------------------------------------------------------------
# Energy and the broken Casimir
# --------------------------------------------------------------------------


# (CF4 and the Cayley variants share RKMK4's vector update: the same energy error.)
ENERGY_STEPS = {
    "LieEuler": [400, 800, 1600, 3200],
    "CG3": [100, 200, 400, 800],
    "LGVI": [100, 200, 400, 800],
    "RKMK4": [100, 200, 400, 800],
    "RKMK45": [25, 50, 100, 200],
}


@pytest.mark.parametrize("name", list(ENERGY_STEPS))
def test_energy_error_has_the_order_of_the_method(name):
    """The energy is conserved by the flow; the methods' error in it scales as dt^order.

    LGVI is no exception here (order 2, not bounded): Suslov's flow is not
    Hamiltonian, and the variational integrator only sees an external torque.
    """
    sc, method = scene(), METHODS[name]()
    ns = np.array(ENERGY_STEPS[name])
    errs = [float(_run(sc, method, T, n)[1]) for n in ns]
    slope = np.polyfit(np.log(T / ns), np.log(errs), 1)[0]
    print(f"{name}: max |E - E0| = {', '.join(f'{e:.1e}' for e in errs)}; slope {slope:.2f}")
    assert abs(slope - method.order) < 0.4
    assert min(errs) > 1e-13  # above round-off: the fit means something


def test_casimir_broken_where_the_free_body_keeps_it(trajectory):
    sc, traj = trajectory
    L = np.linalg.norm(np.asarray(sc.body.body_momentum(traj.Omega)), axis=-1)
    free = so3jax.scenes.free_body(MOMENTS, R0, OMEGA0)
    # LGVI conserves the free body's momentum to round-off.
    tr = so3jax.simulate(free, so3jax.LGVI(), DT, round(T / DT), save_every=SAVE)
    L_free = np.linalg.norm(np.asarray(free.body.body_momentum(tr.Omega)), axis=-1)
    change, change_free = np.ptp(L) / L[0], np.ptp(L_free) / L_free[0]
    print(f"|J Omega| relative change: Suslov {change:.3f}, free body {change_free:.1e}")
    assert change > 0.1
    assert change_free < 1e-13
    # The same start without the constraint goes elsewhere.
    gap = np.abs(np.asarray(traj.Omega[-1]) - np.asarray(tr.Omega[-1])).max()
    assert gap > 0.5


# --------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"Omega0": OMEGA0 + 1e-6 * A}, "Omega0 must satisfy the constraint"),
        ({"Omega0": [1.0, 2.0, 3.0]}, "Omega0 must satisfy the constraint"),
        ({"Omega0": [1.0, 2.0]}, "Omega0 must have shape"),
        ({"Omega0": [np.nan, 0.0, 0.0]}, "Omega0 contains NaN"),
        ({"a": [0.0, 0.0, 0.0]}, "a must be a nonzero vector"),
        ({"a": [1.0, np.inf, 0.0]}, "a contains NaN or inf"),
        ({"a": [1.0, 0.0]}, "a must have shape"),
        ({"a": np.ones((2, 3))}, "a must have shape"),
        ({"inertia": [1.0, -2.0, 3.0]}, "inertia must be positive definite"),
        ({"inertia": [[1.0, 0.5, 0], [0, 2.0, 0], [0, 0, 3.0]]}, "inertia must be symmetric"),
        ({"inertia": np.ones(4)}, "inertia must be"),
        ({"inertia": [1.0, np.nan, 3.0]}, "inertia contains NaN"),
        ({"R0": 2 * np.eye(3)}, "R0 is not a rotation"),
    ],
)
def test_bad_input_raises_naming_the_argument(kwargs, match):
    args = {"inertia": MOMENTS, "a": A, "R0": R0, "Omega0": OMEGA0} | kwargs
    with pytest.raises(ValueError, match=match):
        so3jax.scenes.suslov(**args)


def test_constraint_tolerance_depends_on_dtype():
    a_hat = A / np.linalg.norm(A)
    off = OMEGA0 + 1e-7 * np.linalg.norm(OMEGA0) * a_hat  # 1e-7 relative
    sc = so3jax.scenes.suslov(MOMENTS, A, R0.astype(np.float32), off.astype(np.float32))
    assert abs(float(sc.constraint(sc.y0.x))) < 1e-6  # accepted in float32, then projected
    with pytest.raises(ValueError, match="Omega0"):
        so3jax.scenes.suslov(MOMENTS, A, R0, off)  # rejected in float64
    just = OMEGA0 + 1e-9 * np.linalg.norm(OMEGA0) * a_hat
    sc = so3jax.scenes.suslov(MOMENTS, A, R0, just)
    assert abs(float(sc.constraint(sc.y0.x))) < 1e-15
