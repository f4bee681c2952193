"""The diffrax ambient baseline: agreement, drift off the group, order, transforms."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from exact_rigid_body import ExactFreeBody

import so3jax as s

J = np.array([1.0, 2.0, 3.0])
W0 = np.array([0.5, 1.0, -0.3])
T = 4.0
N_SAVE = 5


@pytest.fixture(scope="module")
def R0():
    return s.exp(jnp.array([0.3, 0.2, -0.1]))


@pytest.fixture(scope="module")
def scene(R0):
    return s.scenes.free_body(jnp.asarray(J), R0, jnp.asarray(W0))


@pytest.fixture(scope="module")
def exact(R0):
    return ExactFreeBody(J, np.asarray(R0), W0)


def _errors(tr, exact):
    """Attitude (geodesic) and |Omega| errors at every saved time against the exact motion."""
    t = np.asarray(tr.t)
    R, W = exact.state(t)
    # The unprojected ambient R is off the group: measure it against R_exact directly.
    e_R = np.linalg.norm(np.asarray(tr.R) - R, axis=(-1, -2))
    e_W = np.linalg.norm(np.asarray(tr.Omega) - W, axis=-1)
    return e_R, e_W


def test_trajectory_fields(scene, R0):
    tr = s.simulate_ambient(scene, "tsit5", T, n_save=N_SAVE)
    assert tr.R.shape == (N_SAVE, 3, 3) and tr.Omega.shape == (N_SAVE, 3)
    np.testing.assert_allclose(tr.t, np.linspace(0, T, N_SAVE))
    np.testing.assert_array_equal(tr.R[0], R0)
    np.testing.assert_array_equal(tr.Omega[0], W0)
    assert tr.Rd is None and tr.M is None
    assert int(tr.status.code) == 0 and int(tr.status.step) == -1
    ex = {k: int(v) for k, v in tr.extras.items()}
    assert ex["num_steps"] == ex["num_accepted_steps"] + ex["num_rejected_steps"] > 0
    # Tsit5 is FSAL: 6 new stages per step, one at the start, two to pick dt0.
    assert ex["num_fevals"] == 6 * ex["num_steps"] + 3
    np.testing.assert_array_equal(tr.y.R[0], tr.R[-1])


@pytest.mark.parametrize("solver", ["tsit5", "dopri5", "dopri8"])
def test_adaptive_agrees_with_exact_and_lie_group(solver, scene, exact):
    """Error shrinks with the tolerance and matches the Lie-group solution."""
    errs = []
    for tol in (1e-6, 1e-10):
        tr = s.simulate_ambient(scene, solver, T, rtol=tol, atol=tol, n_save=N_SAVE)
        assert int(tr.status.code) == 0
        e_R, e_W = _errors(tr, exact)
        errs.append(max(e_R.max(), e_W.max()))
    # A tolerance of 1e-10 over a few periods: global error within ~100x tol;
    # and four decades of tolerance buy at least two decades of accuracy.
    assert errs[1] < 1e-8
    assert errs[1] < 1e-2 * errs[0]
    lie = s.simulate(scene, s.RKMK45(), T / 800, 800, save_every=200)
    np.testing.assert_allclose(tr.R, lie.R, atol=1e-8)
    np.testing.assert_allclose(tr.Omega, lie.Omega, atol=1e-8)


def test_drift_off_the_group_unless_projected(scene):
    """Without projection ||R^T R - I|| grows far above round-off; with it, it stays there."""
    kw = dict(dt=0.05, n_steps=400, save_every=100)
    free = s.simulate_ambient(scene, "rk4", **kw)
    proj = s.simulate_ambient(scene, "rk4", project=True, **kw)
    lie = s.simulate(scene, s.RKMK4(), 0.05, 400, save_every=100)
    d_free = np.asarray(s.orthogonality_error(free.R))
    assert d_free[-1] > 1e-9 and np.all(np.diff(d_free) > 0)
    assert np.asarray(s.orthogonality_error(proj.R)).max() < 1e-14
    assert np.asarray(s.orthogonality_error(lie.R)).max() < 1e-14
    # Adaptive: drift at the level of the tolerance, or round-off when projected.
    ad = s.simulate_ambient(scene, "tsit5", T, rtol=1e-6, atol=1e-6, n_save=N_SAVE)
    ad_p = s.simulate_ambient(scene, "tsit5", T, rtol=1e-6, atol=1e-6, n_save=N_SAVE, project=True)
    assert float(s.orthogonality_error(ad.R[-1])) > 1e-10
    assert np.asarray(s.orthogonality_error(ad_p.R)).max() < 1e-14
    # Projection does not hurt accuracy: both within the tolerance of each other.
    np.testing.assert_allclose(ad_p.Omega, ad.Omega, atol=1e-4)


def test_rk4_tableau_is_classic_rk4():
    """One step on y' = lam y is the degree-4 Taylor polynomial of exp(h lam)."""
    lam, h = -0.7, 0.3
    term = diffrax.ODETerm(lambda t, y, args: lam * y)
    sol = diffrax.diffeqsolve(term, s.RK4(), 0.0, h, h, jnp.array(1.0))
    z = lam * h
    assert float(sol.ys[-1]) == pytest.approx(1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24, rel=1e-15)


def test_rk4_fitted_order(scene, exact):
    dts = np.array([0.08, 0.04, 0.02, 0.01])
    errs = []
    for dt in dts:
        n = int(round(2.0 / dt))
        tr = s.simulate_ambient(scene, "rk4", dt=dt, n_steps=n, save_every=n)
        e_R, e_W = _errors(tr, exact)
        errs.append(max(e_R[-1], e_W[-1]))
    slope = np.polyfit(np.log(dts), np.log(errs), 1)[0]
    assert 3.8 < slope < 4.2, slope


def test_jit_and_vmap(scene, R0):
    Ws = jnp.array([[0.5, 1.0, -0.3], [0.1, -0.2, 0.9], [1.0, 0.0, 0.2]])

    # R0 is passed in, not closed over: the eager input checks of free_body
    # currently trip on concrete arrays inside jit (see the report).
    def run(W, R0):
        sc = s.scenes.free_body(jnp.asarray(J), R0, W)
        tr = s.simulate_ambient(sc, "tsit5", T, n_save=N_SAVE)
        return tr.R[-1], tr.Omega[-1], tr.extras["num_steps"]

    R_b, W_b, n_b = jax.jit(jax.vmap(run, in_axes=(0, None)))(Ws, R0)
    for i in range(3):
        R_i, W_i, n_i = run(Ws[i], R0)
        np.testing.assert_allclose(R_b[i], R_i, atol=1e-13)
        np.testing.assert_allclose(W_b[i], W_i, atol=1e-13)
        assert int(n_b[i]) == int(n_i)

    def run_fixed(W):
        sc = s.scenes.free_body(jnp.asarray(J), R0, W)
        return s.simulate_ambient(sc, "rk4", dt=0.05, n_steps=20, save_every=20).Omega[-1]

    W_b = jax.vmap(run_fixed)(Ws)
    for i in range(3):
        np.testing.assert_allclose(W_b[i], run_fixed(Ws[i]), atol=1e-14)


@pytest.mark.parametrize("mode", ["adaptive", "fixed"])
def test_grad_matches_finite_differences(mode, R0):
    """d/dp of a scalar of the final state, with Omega0 = p * W0."""
    R_target = s.exp(jnp.array([0.1, -0.4, 0.2]))

    def loss(p):
        sc = s.scenes.free_body(jnp.asarray(J), R0, p * jnp.asarray(W0))
        if mode == "adaptive":
            tr = s.simulate_ambient(
                sc, "tsit5", 2.0, rtol=1e-12, atol=1e-12, n_save=2, max_steps=2000
            )
        else:
            tr = s.simulate_ambient(sc, "rk4", dt=0.01, n_steps=200, save_every=200)
        return jnp.sum(tr.R[-1] * R_target) + tr.Omega[-1, 1]

    p, eps = 1.3, 1e-5
    value_and_grad = jax.jit(jax.value_and_grad(loss))  # one program for both
    g = float(value_and_grad(p)[1])
    fd = (float(value_and_grad(p + eps)[0]) - float(value_and_grad(p - eps)[0])) / (2 * eps)
    assert g == pytest.approx(fd, rel=1e-6, abs=1e-8)


def test_failure_is_flagged_not_raised(scene):
    tr = s.simulate_ambient(scene, "tsit5", T, n_save=N_SAVE, max_steps=5)
    assert int(tr.status.code) == 3 and int(tr.status.step) == 5
    assert "max_steps" in tr.status.message()
    assert bool(jnp.all(jnp.isnan(tr.Omega[-1])))
    assert bool(jnp.all(jnp.isfinite(tr.Omega[0]))) and bool(jnp.all(jnp.isfinite(tr.y.x)))
    # A blow-up in fixed steps: frozen at the last good state, flagged with its step.
    fast = s.scenes.free_body(jnp.asarray(J), jnp.eye(3), jnp.array([1e3, 2e3, -1e3]))
    tr = s.simulate_ambient(fast, "rk4", dt=1.0, n_steps=50, save_every=1)
    assert int(tr.status.code) == 1 and 0 <= int(tr.status.step) < 50
    assert bool(jnp.all(jnp.isfinite(tr.y.x))) and bool(jnp.isnan(tr.Omega[-1, 0]))


def test_bad_input(scene):
    with pytest.raises(ValueError, match="solver"):
        s.simulate_ambient(scene, "rk45", T)
    with pytest.raises(ValueError, match="dt and n_steps"):
        s.simulate_ambient(scene, "rk4", T)
    with pytest.raises(ValueError, match="not both"):
        s.simulate_ambient(scene, "tsit5", T, dt=0.1, n_steps=3)
    with pytest.raises(ValueError, match="n_steps"):
        s.simulate_ambient(scene, "tsit5", dt=0.1)
    with pytest.raises(ValueError, match="rtol"):
        s.simulate_ambient(scene, "tsit5", T, rtol=-1.0)
    with pytest.raises(ValueError, match="t1"):
        s.simulate_ambient(scene, "tsit5", -1.0)
    with pytest.raises(ValueError, match="dt"):
        s.simulate_ambient(scene, "rk4", dt=0.0, n_steps=3)
    with pytest.raises(TypeError, match="scene"):
        s.simulate_ambient("free body", "tsit5", T)


@pytest.mark.skipif(not hasattr(s.scenes, "seed"), reason="scenes.seed not available yet")
def test_seed_scenario_agrees_with_lie_group():
    sc = s.scenes.seed()
    t1 = 2.0
    tr = s.simulate_ambient(sc, "tsit5", t1, rtol=1e-10, atol=1e-10, n_save=N_SAVE)
    lie = s.simulate(sc, s.RKMK4(), t1 / 2000, 2000, save_every=500)
    assert int(tr.status.code) == 0
    assert tr.Rd is not None and tr.M is not None
    np.testing.assert_allclose(tr.R, lie.R, atol=1e-7)
    np.testing.assert_allclose(tr.Omega, lie.Omega, atol=1e-6)
    np.testing.assert_allclose(tr.Rd, lie.Rd, atol=1e-7)
    np.testing.assert_allclose(tr.M, lie.M, rtol=1e-6, atol=1e-6)
