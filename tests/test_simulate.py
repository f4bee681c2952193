"""Tests of `simulate`: saving, batching, dtypes, input errors, status, compilation."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from exact_rigid_body import ExactFreeBody, ambient_reference
from scipy.spatial.transform import Rotation

import so3jax
from so3jax import LieState, RigidBody, _engine
from so3jax._engine.passes import scalarize as sc
from so3jax.scenes import MechanicalScene

MOMENTS = np.array([1.0, 1.5, 2.2])
R0 = Rotation.from_rotvec([0.4, -0.3, 0.9]).as_matrix()
OMEGA0 = np.array([0.9, -0.6, 1.3])


def free_body(Omega=OMEGA0, R=R0, inertia=MOMENTS):
    return so3jax.scenes.free_body(inertia, R, Omega)


class ForcedBody(MechanicalScene):
    """A rigid body under the smooth torque ``(sin t, cos 2t, 0.3)``."""

    body: RigidBody
    y0: LieState

    def torque(self, t, y):
        return jnp.stack([jnp.sin(t), jnp.cos(2 * t), 0.3 * jnp.ones_like(t)])


# --------------------------------------------------------------------------
# What comes out
# --------------------------------------------------------------------------


def test_trajectory_layout_and_save_every():
    scene = free_body()
    dt, n = 0.01, 60
    full = so3jax.simulate(scene, so3jax.RKMK4(), dt, n)
    sub = so3jax.simulate(scene, so3jax.RKMK4(), dt, n, save_every=6)
    assert full.R.shape == (n + 1, 3, 3) and full.Omega.shape == (n + 1, 3)
    assert sub.R.shape == (n // 6 + 1, 3, 3) and sub.t.shape == (n // 6 + 1,)
    np.testing.assert_allclose(full.t, dt * np.arange(n + 1), rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(sub.t, full.t[::6], rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(sub.R, full.R[::6], rtol=0, atol=1e-14)
    np.testing.assert_allclose(sub.Omega, full.Omega[::6], rtol=0, atol=1e-14)
    np.testing.assert_array_equal(full.R[0], R0)
    np.testing.assert_array_equal(full.Omega[0], OMEGA0)
    # The final state (for restarting) is the last saved point.
    np.testing.assert_array_equal(full.y.R[0], full.R[-1])
    np.testing.assert_array_equal(full.y.x, full.Omega[-1])
    assert full.Rd is None and full.M is None and full.extras == {}
    assert int(full.status.code) == 0 and int(full.status.step) == -1
    assert bool(full.status.ok)
    assert full.status.message() == "finite to the end"
    # Free body: the spatial momentum is conserved to the method's accuracy.
    ex = ExactFreeBody(MOMENTS, R0, OMEGA0)
    np.testing.assert_allclose(full.Omega, ex.omega(np.asarray(full.t)), atol=1e-8)


def test_restart_from_final_state_continues_the_run():
    scene = free_body()
    one = so3jax.simulate(scene, so3jax.RKMK4(), 0.01, 60)
    half = so3jax.simulate(scene, so3jax.RKMK4(), 0.01, 30)
    scene2 = so3jax.scenes.free_body(MOMENTS, half.y.R[0], half.y.x)
    rest = so3jax.simulate(scene2, so3jax.RKMK4(), 0.01, 30, t0=half.t[-1])
    np.testing.assert_allclose(rest.t, one.t[30:], rtol=1e-14)
    np.testing.assert_allclose(rest.R, one.R[30:], atol=1e-14)


def test_time_dependent_torque_sees_t0():
    """A forced run from t0 matches a DOP853 reference started at t0 (t is threaded right)."""
    t0, dt, n = 1.3, 0.01, 200
    scene = ForcedBody(
        body=RigidBody(jnp.asarray(MOMENTS)),
        y0=LieState(jnp.asarray(R0)[None], jnp.asarray(OMEGA0)),
    )
    tr = so3jax.simulate(scene, so3jax.RKMK4(), dt, n, save_every=50, t0=t0)
    np.testing.assert_allclose(tr.t, t0 + dt * np.arange(0, n + 1, 50), rtol=1e-14)
    torque = lambda t: np.array([np.sin(t), np.cos(2 * t), 0.3])
    R_ref, W_ref = ambient_reference(MOMENTS, R0, OMEGA0, np.asarray(tr.t), torque=torque)
    np.testing.assert_allclose(tr.R, R_ref, atol=1e-9)
    np.testing.assert_allclose(tr.Omega, W_ref, atol=1e-9)


# --------------------------------------------------------------------------
# Batches, dtypes, transforms
# --------------------------------------------------------------------------


def _batch_inputs(n=4, seed=0):
    rng = np.random.default_rng(seed)
    Rs = Rotation.random(n, random_state=rng).as_matrix()
    Ws = rng.normal(size=(n, 3))
    return Rs, Ws


def test_vmap_over_initial_conditions_equals_loop():
    Rs, Ws = _batch_inputs()
    method, dt, n = so3jax.RKMK4(), 0.02, 50

    def run(R, W):
        return so3jax.simulate(so3jax.scenes.free_body(MOMENTS, R, W), method, dt, n, save_every=5)

    batch = jax.vmap(run)(jnp.asarray(Rs), jnp.asarray(Ws))
    assert batch.R.shape == (4, n // 5 + 1, 3, 3)
    assert batch.status.code.shape == (4,)
    for i in range(4):
        single = run(Rs[i], Ws[i])
        np.testing.assert_allclose(batch.R[i], single.R, rtol=0, atol=1e-14)
        np.testing.assert_allclose(batch.Omega[i], single.Omega, rtol=0, atol=1e-14)
        np.testing.assert_allclose(batch.t[i], single.t, rtol=1e-15)
        assert int(batch.status.code[i]) == 0


def test_vmap_over_step_size_equals_loop():
    dts = np.array([0.01, 0.02, 0.05])
    scene = free_body()
    batch = jax.vmap(lambda dt: so3jax.simulate(scene, so3jax.CF4(), dt, 20))(jnp.asarray(dts))
    for i, dt in enumerate(dts):
        single = so3jax.simulate(scene, so3jax.CF4(), dt, 20)
        np.testing.assert_allclose(batch.R[i], single.R, rtol=0, atol=1e-14)
        np.testing.assert_allclose(batch.t[i], single.t, rtol=1e-15)


@pytest.mark.parametrize(
    "method", [so3jax.RKMK4(), so3jax.LGVI(), so3jax.CG3()], ids=lambda m: m.name
)
def test_float32_runs_stay_float32_and_on_the_group(method):
    f32 = np.float32
    scene = so3jax.scenes.free_body(MOMENTS.astype(f32), R0.astype(f32), OMEGA0.astype(f32))
    tr = so3jax.simulate(scene, method, 0.01, 200, save_every=20)
    for leaf in (tr.t, tr.R, tr.Omega, tr.y.R, tr.y.x):
        assert leaf.dtype == jnp.float32
    assert int(tr.status.code) == 0
    R = np.asarray(tr.R, dtype=np.float64)
    orth = np.linalg.norm(R.transpose(0, 2, 1) @ R - np.eye(3), axis=(1, 2))
    assert orth.max() <= 1e-5, orth.max()  # float32 round-off random walk: ~1e-6 after 100 steps
    assert np.abs(np.linalg.det(R) - 1).max() <= 1e-5
    # Agrees with the float64 run to float32 accuracy.
    tr64 = so3jax.simulate(free_body(), method, 0.01, 200, save_every=20)
    np.testing.assert_allclose(R, tr64.R, atol=2e-5)


def test_grad_through_simulate_matches_finite_differences():
    method, dt, n = so3jax.LieEuler(), 0.05, 20  # cheapest to compile; the loop is the same
    w = jnp.asarray(np.random.default_rng(2).normal(size=(3, 3)))

    def loss(W0):
        tr = so3jax.simulate(so3jax.scenes.free_body(MOMENTS, R0, W0), method, dt, n, save_every=n)
        return jnp.sum(w * tr.R[-1]) + jnp.sum(tr.Omega[-1] ** 2)

    g = jax.jit(jax.grad(loss))(jnp.asarray(OMEGA0))
    eps = 1e-6
    W_pm = OMEGA0 + eps * np.concatenate([np.eye(3), -np.eye(3)])
    values = np.asarray(jax.jit(jax.vmap(loss))(jnp.asarray(W_pm)))
    fd = (values[:3] - values[3:]) / (2 * eps)
    np.testing.assert_allclose(g, fd, rtol=1e-7, atol=1e-8)


# --------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------


@pytest.mark.parametrize("dt", [0.0, -0.1, np.nan, np.inf])
def test_rejects_bad_dt(dt):
    with pytest.raises(ValueError, match="dt must be positive"):
        so3jax.simulate(free_body(), so3jax.LieEuler(), dt, 10)


def test_rejects_dt_that_is_zero_in_the_runs_dtype():
    """``dt`` is checked in the scene's dtype: 1e-50 is 0 in float32, 1e300 is inf."""
    sc = so3jax.scenes.seed(dtype=jnp.float32)
    for dt in (1e-50, 1e300):
        with pytest.raises(ValueError, match="dt must be positive and finite"):
            so3jax.simulate(sc, so3jax.LieEuler(), dt, 10)


def test_rejects_non_scalar_dt():
    with pytest.raises(ValueError, match="dt must be a scalar"):
        so3jax.simulate(free_body(), so3jax.LieEuler(), jnp.array([0.1, 0.2]), 10)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n_steps": 0}, "n_steps must be >= 1"),
        ({"n_steps": -3}, "n_steps must be >= 1"),
        ({"n_steps": 2.5}, "n_steps must be an integer"),
        ({"n_steps": 10.0}, "n_steps must be an integer"),
        ({"n_steps": "10"}, "n_steps must be an integer"),
        ({"n_steps": 10, "save_every": 0}, "save_every must be >= 1"),
        ({"n_steps": 10, "save_every": 1.5}, "save_every must be an integer"),
        ({"n_steps": 10, "save_every": 3}, "multiple of save_every"),
    ],
)
def test_rejects_bad_step_counts(kwargs, match):
    with pytest.raises(ValueError, match=match):
        so3jax.simulate(free_body(), so3jax.LieEuler(), 0.1, **kwargs)


def test_accepts_numpy_integers():
    tr = so3jax.simulate(free_body(), so3jax.LieEuler(), 0.1, np.int64(4), save_every=np.int32(2))
    assert tr.R.shape == (3, 3, 3)


@pytest.mark.parametrize(
    "R, match",
    [
        (2.0 * np.eye(3), "project"),
        (np.diag([1.0, 1.0, -1.0]), "project"),
        (R0 + 1e-4, "project"),
        (np.eye(2), "shape"),
        (np.stack([R0, R0]), "shape"),
        (np.where(np.eye(3) > 0, np.nan, 0.0), "NaN"),
    ],
)
def test_rejects_bad_initial_attitude(R, match):
    with pytest.raises(ValueError, match=match):
        free_body(R=R)


@pytest.mark.parametrize(
    "Omega, match",
    [
        (np.array([np.nan, 0.0, 1.0]), "NaN"),
        (np.array([0.0, np.inf, 1.0]), "inf"),
        (np.ones(4), "shape"),
    ],
)
def test_rejects_bad_initial_rate(Omega, match):
    with pytest.raises(ValueError, match=match):
        free_body(Omega=Omega)


def test_rejects_wrong_scene_or_method():
    with pytest.raises(TypeError, match="scene"):
        so3jax.simulate("free body", so3jax.RKMK4(), 0.1, 10)
    with pytest.raises(TypeError, match="method"):
        so3jax.simulate(free_body(), so3jax.RKMK4, 0.1, 10)  # the class, not an instance


def _run_traced_dt(dt):
    return so3jax.simulate(free_body(), so3jax.LieEuler(), dt, 10)


_JITTED = {"jax.jit": jax.jit(_run_traced_dt), "eqx.filter_jit": eqx.filter_jit(_run_traced_dt)}


@pytest.mark.parametrize(
    "jit, dt",
    [("jax.jit", -0.1), ("jax.jit", 0.0), ("jax.jit", np.nan), ("eqx.filter_jit", -0.1)],
)
def test_traced_bad_dt_is_a_status_under_jit(jit, dt):
    """A traced ``dt`` is checked in the run: its status names it and its points are NaN.
    (`eqx.filter_jit` keeps a Python float static: it is checked while tracing.)"""
    run = _JITTED[jit]
    assert np.all(np.isfinite(run(0.1).R))
    if jit == "eqx.filter_jit":
        with pytest.raises(ValueError, match="dt must be positive"):
            run(dt)
        dt = jnp.asarray(dt)
    traj = run(dt)
    assert traj.status.message() == "dt is not positive and finite (before the first step)"
    assert np.all(np.isnan(np.asarray(traj.R)))


@pytest.mark.parametrize("dt", [-0.1, np.nan, np.float32(0.0)])
def test_constant_bad_dt_raises_while_tracing(dt):
    """A Python or NumPy ``dt`` under the caller's ``jit`` is checked before it is staged."""
    with pytest.raises(ValueError, match="dt must be positive"):
        jax.jit(lambda R0: so3jax.simulate(free_body(), so3jax.LieEuler(), dt, 4, R0=R0).R)(
            jnp.eye(3)
        )


def test_programs_with_a_constant_dt_have_no_host_callback():
    """JAX's persistent compilation cache does not store a program with a host callback
    (`eqx.error_if` has one): with ``dt`` a Python float, the programs users jit (a batch
    of `simulate`, the gradient of `expected_cost`, fixed-step `simulate_ambient`) have none,
    and neither has a run whose ``dt`` is traced: its check is a `Status` code."""
    sc = so3jax.scenes.seed()
    R0s = so3jax.random_rotation(jax.random.key(0), (4,))
    R0, W0 = so3jax.initial_states(jax.random.key(1), 2)

    def callbacks(fn, *args):
        return str(jax.make_jaxpr(fn)(*args)).count("callback")

    def batch(R0s):
        return jax.vmap(lambda R: so3jax.simulate(sc, so3jax.RKMK4(), 0.01, 4, 2, R0=R).R)(R0s)

    def cost(k):
        return so3jax.expected_cost(sc, k[0], k[1], R0, W0, so3jax.RKMK4(), 1e-2, 4)

    def ambient(scene):
        return so3jax.simulate_ambient(scene, "rk4", dt=0.01, n_steps=4).R

    assert callbacks(batch, R0s) == 0
    assert callbacks(jax.grad(cost), jnp.array([8.81, 2.54])) == 0
    assert callbacks(ambient, sc) == 0
    assert callbacks(lambda h: _run_traced_dt(h).R, 0.1) == 0  # a traced dt: a status


# --------------------------------------------------------------------------
# Divergence is a status, not an exception, and stays in its own run
# --------------------------------------------------------------------------

BLOWUP_DT = 0.5  # Lie–Euler is unstable at this step for OMEGA0


def test_divergence_is_reported_with_the_step():
    scene = free_body()
    n = 60
    tr = so3jax.simulate(scene, so3jax.LieEuler(), BLOWUP_DT, n)
    assert int(tr.status.code) == 1
    k = int(tr.status.step)
    assert 0 < k < n
    assert tr.status.message() == (
        f"the state stopped being finite at step {k} (t = {k * BLOWUP_DT:.6g})"
    )
    assert not bool(tr.status.ok)
    finite = np.isfinite(np.asarray(tr.R)).all(axis=(1, 2))
    # Points 0..k (the state at t0 + k dt was the last good one) are kept, NaN after.
    assert finite[: k + 1].all() and not finite[k + 1 :].any()
    assert np.isnan(np.asarray(tr.Omega[k + 1 :])).all()
    assert np.isfinite(np.asarray(tr.t)).all()
    # The final state is frozen at the last good one ...
    np.testing.assert_array_equal(tr.y.R[0], tr.R[k])
    # ... which a run of exactly k steps reproduces, finite to the end;
    short = so3jax.simulate(scene, so3jax.LieEuler(), BLOWUP_DT, k)
    assert int(short.status.code) == 0
    np.testing.assert_allclose(short.R, tr.R[: k + 1], rtol=0, atol=1e-12)
    # and the next Lie–Euler step from it is indeed not finite.
    W = np.asarray(short.Omega[-1])
    W1 = W + BLOWUP_DT * np.asarray(scene.body.euler_rhs(jnp.asarray(W)))
    assert not np.isfinite(W1).all() or not np.isfinite(np.asarray(so3jax.exp(BLOWUP_DT * W))).all()


def test_divergent_tracking_run_masks_its_own_points_only():
    """In a batch of tracking runs that share the reference, the one that blows up has
    NaN for every observation (the reference attitude too) from the first point saved
    after its failed step; the others equal their single runs."""
    sc = so3jax.scenes.seed()
    gains = jnp.array([[3.0, 1.5], [3.0, 1e5]])  # the second is far past the stable step

    def run(k):
        from so3jax._tune import with_gains

        return so3jax.simulate(with_gains(sc, k[0], k[1]), so3jax.LieEuler(), 0.05, 60, 3)

    batch = jax.vmap(run)(gains)
    bad = int(batch.status.step[1])
    assert int(batch.status.code[0]) == 0 and int(batch.status.code[1]) != 0
    keep = 3 * np.arange(21) <= bad
    assert keep.any() and not keep.all()
    for f in ("R", "Rd", "Omega", "M"):
        a = np.asarray(getattr(batch, f)[1])
        finite = np.isfinite(a).reshape(len(keep), -1).all(axis=1)
        np.testing.assert_array_equal(finite, keep, err_msg=f)
        assert np.isnan(a[~keep]).all(), f
        np.testing.assert_array_equal(getattr(batch, f)[0], getattr(run(gains[0]), f))
    np.testing.assert_array_equal(batch.Rd[1][keep], batch.Rd[0][keep])
    assert np.isfinite(np.asarray(batch.t)).all()


def test_divergent_run_does_not_poison_the_batch():
    scales = np.array([1.0, 0.5, 40.0, 1.5])  # the third diverges at dt = 0.05
    Ws = scales[:, None] * OMEGA0
    method, dt, n = so3jax.LieEuler(), 0.05, 40

    def run(W):
        return so3jax.simulate(free_body(Omega=W), method, dt, n, save_every=4)

    batch = jax.vmap(run)(jnp.asarray(Ws))
    codes = np.asarray(batch.status.code)
    np.testing.assert_array_equal(codes, [0, 0, 1, 0])
    np.testing.assert_array_equal(np.asarray(batch.status.step)[[0, 1, 3]], -1)
    # a point is NaN exactly when it was saved after the failed step
    saved_after = 4 * np.arange(n // 4 + 1)
    finite = np.isfinite(np.asarray(batch.R[2])).all(axis=(1, 2))
    np.testing.assert_array_equal(finite, saved_after <= int(batch.status.step[2]))
    assert not finite[-1]
    for i in (0, 1, 3):
        single = run(Ws[i])
        assert np.isfinite(np.asarray(batch.R[i])).all()
        np.testing.assert_allclose(batch.R[i], single.R, rtol=0, atol=1e-14)
    bad = run(Ws[2])
    assert int(bad.status.code) == 1
    assert int(bad.status.step) == int(batch.status.step[2])


# --------------------------------------------------------------------------
# Compilation does not grow with n_steps
# --------------------------------------------------------------------------


def _count_eqns(jaxpr) -> int:
    """Equations of a jaxpr, counting those inside sub-jaxprs (scan, pjit, cond ...)."""
    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
    total = 0
    for eqn in jaxpr.eqns:
        total += 1
        for value in eqn.params.values():
            for sub in value if isinstance(value, list | tuple) else [value]:
                if hasattr(sub, "eqns") or hasattr(getattr(sub, "jaxpr", None), "eqns"):
                    total += _count_eqns(sub)
    return total


def _scan_lengths(jaxpr) -> list[int]:
    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
    out = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "scan":
            out.append(eqn.params["length"])
        for value in eqn.params.values():
            for sub in value if isinstance(value, list | tuple) else [value]:
                if hasattr(sub, "eqns") or hasattr(getattr(sub, "jaxpr", None), "eqns"):
                    out += _scan_lengths(sub)
    return out


@pytest.mark.parametrize("method", [so3jax.RKMK4(), so3jax.LGVI()], ids=lambda m: m.name)
def test_program_size_does_not_grow_with_n_steps(method):
    scene = free_body()
    jaxprs = {
        (n, k): jax.make_jaxpr(lambda sc, n=n, k=k: so3jax.simulate(sc, method, 0.01, n, k).R)(
            scene
        )
        for n, k in [(10, 1), (10_000, 1), (10_000, 100)]
    }
    counts = {key: _count_eqns(j) for key, j in jaxprs.items()}
    assert counts[(10, 1)] == counts[(10_000, 1)], counts
    # save_every > 1 adds the inner scan of a save block, nothing per step
    assert 0 <= counts[(10_000, 100)] - counts[(10, 1)] <= 2, counts
    assert counts[(10, 1)] > 50  # the counter does look inside the scans
    assert sorted(_scan_lengths(jaxprs[(10_000, 100)])) == [100, 100]


def _scan_carries(jaxpr):
    """The carry avals of every `scan` in ``jaxpr``, nested ones included."""
    out = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "scan":
            nc, ncar = sc.scan_split(eqn)
            out.append([v.aval for v in eqn.invars[nc : nc + ncar]])
        for p in eqn.params.values():
            for sub in p if isinstance(p, (tuple, list)) else (p,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    out += _scan_carries(inner)
    return out


def _unbatched_floats(fn, *args) -> int:
    """Unbatched float scalars in the carry of ``vmap(fn)``'s scalarized step loop."""
    carries = _scan_carries(jax.make_jaxpr(jax.vmap(fn))(*args).jaxpr)
    flat = max(carries, key=len)  # the scalarized step loop: one carry per component
    return sum(a.shape == () and jnp.issubdtype(a.dtype, jnp.floating) for a in flat)


def test_batched_runs_share_the_reference_attitude():
    """Runs that share Rd's start carry it unbatched: integrated once per batch, not per run."""
    from so3jax._simulate import simulate_from
    from so3jax._tune import with_gains, with_initial_state, with_start

    sc = so3jax.scenes.seed()
    method, dt, n = so3jax.RKMK4(), 0.01, 8
    # batches large enough for the scalarized program (smaller ones run the array program)
    B = _engine.policy.batched_layout("run")[0]
    R0, W0 = so3jax.initial_states(0, B)
    k = jnp.linspace(2.0, 8.0, B)

    def starts(R, W):  # a batch of starts (what sweep and expected_cost run)
        sc1, R1 = with_start(sc, R, W)
        return simulate_from(sc1, R1, method, dt, n).R

    def gains(k):  # a gain sweep from one start, through the public simulate
        return so3jax.simulate(with_gains(sc, k, 1.0), method, dt, n).R

    for fn, args in ((starts, (R0, W0)), (gains, (k,))):
        assert _unbatched_floats(fn, *args) >= 9  # Rd's 9 components
    # ... and the numbers are those of runs one at a time (a small batch: array program).
    R0, W0 = R0[:3], W0[:3]
    batch = jax.vmap(starts)(R0, W0)
    for b in range(3):
        one = so3jax.simulate(with_initial_state(sc, R0[b], W0[b]), method, dt, n).R
        np.testing.assert_allclose(batch[b], one, rtol=0, atol=1e-14)


def test_restarted_runs_reuse_the_compiled_program():
    """`simulate` is jitted: a run from another state of the same shapes traces nothing."""
    traces = []

    class Counted(ForcedBody):
        def torque(self, t, y):
            traces.append(None)
            return super().torque(t, y)

    fb = free_body()
    sc = Counted(body=fb.body, y0=fb.y0)
    tr = so3jax.simulate(sc, so3jax.RKMK4(), 0.01, 5)
    n = len(traces)
    assert n > 0
    tr2 = so3jax.simulate(eqx.tree_at(lambda s: s.y0, sc, tr.y), so3jax.RKMK4(), 0.01, 5, t0=0.05)
    assert len(traces) == n
    assert not np.allclose(tr2.R, tr.R)


def test_start_arguments_run_the_scene_built_from_that_start():
    """`simulate(scene, R0=, Omega0=)` equals the run of the scene built from that start.

    Against each scene's own builder: the seed, a hysteretic quaternion controller (its
    memory depends on R0; adaptive steps take the rebuilt scene), and a quadrotor with
    sampled control (no time-driven group: the start is written into the scene before its
    first sample).
    """
    from so3jax._quadrotor import quadrotor_recovery
    from so3jax._simulate import start_scene
    from so3jax.scenes import tracking

    R, W = so3jax.exp(jnp.array([2.0, -1.0, 0.5])), jnp.array([0.3, -0.2, 0.1])

    def rebuilt(sc):  # the same body, controller and reference, from (R, W)
        return tracking(sc.body, sc.controller, R, W, sc.y0.R[1], sc.reference)

    seed, uw = so3jax.scenes.seed(), so3jax.scenes.unwinding(hysteresis=True)
    for scene in (seed, uw):
        a = so3jax.simulate(scene, so3jax.RKMK4(), 0.01, 40, 10, R0=R, Omega0=W)
        b = so3jax.simulate(rebuilt(scene), so3jax.RKMK4(), 0.01, 40, 10)
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
            np.testing.assert_allclose(x, y, rtol=0, atol=1e-14)
    # Adaptive steps run the scene with the start written in: the rebuilt scene's y0.
    for x, y in zip(jax.tree.leaves(start_scene(uw, R, W, apart=False)[0].y0),
                    jax.tree.leaves(rebuilt(uw).y0), strict=True):  # fmt: skip
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-15)
    assert float(uw.y0.x[3]) == 1.0  # the memory is h = 1 and the lifted quaternion of R0
    q = np.asarray(so3jax.simulate(uw, so3jax.RKMK4(), 0.01, 1, R0=R).extras["q_lift"][0])
    assert abs(abs(q @ np.asarray(so3jax.to_quat(R))) - 1) < 1e-12  # R0's, not the scene's
    # A sampled quadrotor has no time-driven group and samples its held control from
    # y0 (`for_step`): the start is written into y0 first, rates included.
    rec = quadrotor_recovery(control_period=0.01)
    started, apart = start_scene(rec, R, W)
    assert apart is None
    np.testing.assert_array_equal(started.y0.R, R[None])
    np.testing.assert_array_equal(started.y0.x, rec.y0.x.at[:3].set(W))
    assert start_scene(seed, R)[1] is not None  # the seed keeps R0 apart (Rd shared)


def test_start_arguments_share_the_reference_under_vmap():
    """Under vmap over `R0` the reference attitude stays unbatched; vmap equals single runs."""
    sc = so3jax.scenes.seed()
    method, dt, n = so3jax.RKMK4(), 0.01, 8
    B = _engine.policy.batched_layout("run")[0]
    R0, W0 = so3jax.initial_states(0, B)

    def public(R, W):
        return so3jax.simulate(sc, method, dt, n, R0=R, Omega0=W).R

    def written(R, W):  # the start written into the scene: Rd batched with it
        y0 = LieState(sc.y0.R.at[0].set(R), sc.y0.x.at[:3].set(W))
        return so3jax.simulate(eqx.tree_at(lambda s: s.y0, sc, y0), method, dt, n).R

    assert _unbatched_floats(public, R0, W0) >= 9  # Rd's 9 components, once for the batch
    assert _unbatched_floats(written, R0, W0) < 9
    batch = jax.vmap(public)(R0, W0)
    for b in (0, B - 1):
        np.testing.assert_allclose(batch[b], public(R0[b], W0[b]), rtol=0, atol=1e-14)
        np.testing.assert_allclose(batch[b], written(R0[b], W0[b]), rtol=0, atol=1e-14)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(R0=jnp.ones((3, 3))), "R0 is not a rotation"),
        (dict(R0=jnp.eye(4)), "R0 must have shape"),
        (dict(Omega0=jnp.zeros(4)), "Omega0 must have shape"),
        (dict(R0=jnp.ones((3, 3)), t1=1.0, rtol=1e-6, atol=1e-6), "R0 is not a rotation"),
    ],
)
def test_start_arguments_reject_bad_input(kw, match):
    """Checked on both paths (the last case: adaptive steps)."""
    steps = {} if "t1" in kw else dict(dt=0.01, n_steps=2)
    with pytest.raises(ValueError, match=match):
        so3jax.simulate(so3jax.scenes.seed(), so3jax.RKMK45(), **steps, **kw)
