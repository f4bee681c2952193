"""Adaptive Lie-group stepping: embedded RKMK pairs as diffrax solvers, `simulate` with tolerances.

References are independent of the code under test: the exact free-body motion
(Jacobi elliptic functions, `exact_rigid_body.py`), a plain diffrax Tsit5 run in
the ambient space R^9 x R^9 x R^3 written here, and central finite differences.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from exact_rigid_body import ExactFreeBody

import so3jax as s

MOMENTS = np.array([1.0, 2.0, 3.0])
R0 = np.asarray(s.exp(jnp.array([0.3, 0.2, -0.1])))
OMEGA0 = np.array([0.5, 1.0, -0.3])


@pytest.fixture(scope="module")
def free():
    return s.scenes.free_body(jnp.asarray(MOMENTS), jnp.asarray(R0), jnp.asarray(OMEGA0))


@pytest.fixture(scope="module")
def exact():
    return ExactFreeBody(MOMENTS, R0, OMEGA0)


def _slope(x, y):
    return np.polyfit(np.log(np.asarray(x)), np.log(np.asarray(y)), 1)[0]


def _angle(R, R_ref):
    return np.asarray(s.geodesic_distance(jnp.asarray(R), jnp.asarray(R_ref)))


# --------------------------------------------------------------------------
# Fixed-step orders through the diffrax solver path
# --------------------------------------------------------------------------


@eqx.filter_jit
def _fixed_run(scene, method, h, T, thetas):
    sol = diffrax.diffeqsolve(
        s.lie_term(scene),
        s.diffrax_solver(method),
        0.0,
        T,
        h,
        scene.y0,
        stepsize_controller=diffrax.ConstantStepSize(),
        saveat=diffrax.SaveAt(ts=thetas * T),
        max_steps=128,
    )
    return sol.ys.R[:, 0], sol.ys.x


# Saved times: step ends (theta = 1) and points inside steps (dense output) for every h below.
THETAS = jnp.array([0.13, 0.5, 0.61, 0.9, 1.0])


@pytest.mark.parametrize(
    "method, order, dense_order, hs",
    [
        (s.RKMK45(), 5, 5, (0.4, 0.2, 0.1, 0.05)),
        (s.RKMK45(embedded=True), 4, 4, (0.4, 0.2, 0.1, 0.05)),
        (s.RKMK32(), 3, 3, (0.2, 0.1, 0.05, 0.025)),
        (s.RKMK32(embedded=True), 2, 2, (0.2, 0.1, 0.05, 0.025)),
        (s.RKMKTsit5(), 5, 4, (0.2, 0.1, 0.05, 0.025)),
        (s.RKMKTsit5(coords="cayley"), 5, 4, (0.2, 0.1, 0.05, 0.025)),
        (s.RKMK45(coords="cayley"), 5, 5, (0.4, 0.2, 0.1, 0.05)),
    ],
    ids=[
        "RKMK45-5",
        "RKMK45-embedded-4",
        "RKMK32-3",
        "RKMK32-embedded-2",
        "RKMKTsit5-5",
        "RKMKTsit5-cayley-5",
        "RKMK45-cayley-5",
    ],
)
def test_fixed_step_orders_of_both_members(free, exact, method, order, dense_order, hs):
    # Through diffrax with ConstantStepSize. At the step ends the error is O(h^p); inside
    # the steps (dense output) it is O(h^p) + the interpolant's local error: O(h^5) for
    # the quartic of RKMK45, O(h^4) for the cubic Hermite interpolants in the algebra of
    # the others. A linear blend of the end points would give O(h^2).
    T = 3.2
    ts = np.asarray(THETAS) * T
    R_ref, W_ref = exact.state(ts)
    end, inside = [], []
    for h in hs:
        R, x = _fixed_run(free, method, jnp.asarray(h), jnp.asarray(T), THETAS)
        assert np.max(np.asarray(s.orthogonality_error(R))) < 1e-14
        err = np.maximum(_angle(R, R_ref), np.max(np.abs(np.asarray(x) - W_ref), -1))
        end.append(err[-1])
        inside.append(np.max(err[:-1]))
    assert end[-1] > 1e-13  # still above round-off: the slope is meaningful
    assert order - 0.3 < _slope(hs, end) < order + 0.6, end
    assert dense_order - 0.5 < _slope(hs, inside) < dense_order + 0.6, inside


def test_solver_kinds():
    assert isinstance(s.diffrax_solver(s.RKMK45()), diffrax.AbstractAdaptiveSolver)
    assert isinstance(s.diffrax_solver(s.RKMK32()), s.DiffraxLieAdaptiveSolver)
    assert isinstance(s.diffrax_solver(s.RKMKTsit5()), s.DiffraxLieAdaptiveSolver)
    for m in (s.RKMK4(), s.CG3(), s.LGVI(), s.RKMK45(embedded=True)):
        solver = s.diffrax_solver(m)
        assert isinstance(solver, s.DiffraxLieSolver)
        assert not isinstance(solver, diffrax.AbstractAdaptiveSolver)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_adaptive_step_loops_over_stages(dtype):
    """The adaptive solvers run stages 1 .. s-1 as one loop (the vector field traced once
    a step): the same stages as the unrolled ones, to round-off, for every pair, both
    coordinates, exact and truncated dexp^-1; on the seed (controller, reference)."""
    from so3jax._integrators import _rkmk as RK

    scene = s.scenes.seed(dtype=dtype)
    y0 = scene.y0  # moved off the start: every stage sees a nonzero error and rate
    R = y0.R @ s.exp(jnp.array([0.4, -1.1, 0.7], dtype))
    y = s.LieState(R, y0.x + jnp.linspace(-0.3, 0.5, y0.x.size, dtype=dtype))
    t, h = jnp.asarray(0.3, dtype), jnp.asarray(0.05, dtype)
    f0 = scene.vector_field(t, y)
    # (float32: the controller's gains and cancellations amplify round-off about 1000x)
    eps = 1e-13 if dtype == jnp.float64 else 1e-4
    for m in (s.RKMK45(), s.RKMKTsit5(coords="cayley"), s.RKMK32(dexpinv="truncated")):
        args = (m.tableau, m.dexpinv == "exact", scene, t, y, h)
        kts, dxs, f = RK.rkmk_stages_looped(*args, f0, m.coords)
        ref = RK.rkmk_stages(*args, f0=f0, return_last=True, coords=m.coords)
        assert len(kts) == len(dxs) == m.tableau.stages
        wants = [*ref[0], *ref[1], ref[2].xi, ref[2].dx]
        for got, want in zip([*kts, *dxs, f.xi, f.dx], wants, strict=True):
            assert got.dtype == dtype
            np.testing.assert_allclose(got, want, rtol=0, atol=eps * np.abs(want).max())

    # One evaluation traced for the first stage and one inside the loop, whatever s.
    calls = []
    term = s.LieTerm(lambda t, y, args: calls.append(t) or scene.vector_field(t, y))
    solver = s.diffrax_solver(s.RKMK45())
    state = solver.init(term, t, t + h, y, None)
    calls.clear()
    jax.make_jaxpr(lambda y: solver.step(term, t, t + h, y, None, state, True)[0])(y)
    assert len(calls) == 2, calls  # (made_jump: the first stage is evaluated afresh)


def test_fixed_step_wrapper_matches_simulate(free):
    # The diffrax wrapper of a fixed-step method takes exactly the steps `simulate`
    # takes; LGVI also needs the scene itself (body, torque), found inside the term.
    h, n = 0.05, 40
    R, x = _fixed_run(free, s.LGVI(), jnp.asarray(h), jnp.asarray(h * n), THETAS)
    tr = s.simulate(free, s.LGVI(), h, n)
    assert np.max(np.abs(np.asarray(R[-1]) - np.asarray(tr.R[-1]))) < 1e-12
    assert np.max(np.abs(np.asarray(x[-1]) - np.asarray(tr.Omega[-1]))) < 1e-12
    assert np.max(np.asarray(s.orthogonality_error(R))) < 1e-14


# --------------------------------------------------------------------------
# Adaptive: tolerance proportionality, on the group at every saved time
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "method",
    [s.RKMK45(), s.RKMK32(), s.RKMKTsit5(coords="cayley")],
    ids=["RKMK45", "RKMK32", "RKMKTsit5-cayley"],
)
def test_tolerance_proportionality_and_group(free, exact, method):
    T = 10.0
    ts = np.linspace(0.0, T, 57)  # not aligned with the steps: dense output
    R_ref, W_ref = exact.state(ts)
    tols = (1e-5, 1e-6, 1e-7, 1e-8)
    final, steps = [], []
    for tol in tols:
        tr = s.simulate(free, method, t1=T, rtol=tol, atol=tol, saveat=ts)
        assert tr.status.message() == "finite to the end"
        assert np.max(np.asarray(s.orthogonality_error(tr.R))) <= 1e-13
        err = _angle(tr.R, R_ref)
        # Every saved point, interpolated ones included, is as accurate as the tolerance says.
        assert np.max(err) < 300 * tol
        assert np.max(np.abs(np.asarray(tr.Omega) - W_ref)) < 300 * tol
        final.append(err[-1])
        steps.append(int(tr.extras["num_accepted_steps"]))
    assert 0.7 < _slope(tols, final) < 1.3, final
    assert steps == sorted(steps)  # tighter tolerance, more steps


def test_extras_and_counts(free):
    ts = np.linspace(0.0, 10.0, 57)  # the shapes of the test above: no new compilation
    tr = s.simulate(free, s.RKMK45(), t1=10.0, rtol=1e-7, saveat=ts)
    ex = {k: int(v) for k, v in tr.extras.items()}
    assert ex["num_steps"] == ex["num_accepted_steps"] + ex["num_rejected_steps"]
    # FSAL: 1 evaluation at the start, 2 for the initial step choice, 6 per attempted step.
    assert ex["num_fevals"] == 6 * ex["num_steps"] + 3
    assert tr.R.shape == (57, 3, 3) and tr.Omega.shape == (57, 3) and tr.t.shape == (57,)
    assert np.allclose(tr.t, ts)
    # The saved state at t1 restarts the run.
    assert np.allclose(tr.y.R[0], tr.R[-1]) and np.allclose(tr.y.x, tr.Omega[-1])


def test_max_steps_flags_the_run(free):
    tr = s.simulate(free, s.RKMK32(), t1=10.0, rtol=1e-10, saveat=11, max_steps=5)
    assert int(tr.status.code) == 3 and not bool(tr.status.ok)
    assert "max_steps" in tr.status.message()
    assert int(tr.status.step) >= 1
    assert np.all(np.isnan(np.asarray(tr.R[-1])))
    assert np.isfinite(np.asarray(tr.R[0])).all()


def test_backward_in_time_returns(free):
    # Integrate forward, then backward with diffrax's time reversal: back to the start.
    term, solver = s.lie_term(free), s.diffrax_solver(s.RKMK45())
    ctrl = diffrax.PIDController(rtol=1e-10, atol=1e-10)
    run = eqx.filter_jit(
        lambda t0, t1, y0: diffrax.diffeqsolve(
            term, solver, t0, t1, None, y0, stepsize_controller=ctrl
        )
    )
    zero, three = jnp.asarray(0.0), jnp.asarray(3.0)
    y1 = jax.tree.map(lambda a: a[-1], run(zero, three, free.y0).ys)
    bwd = run(three, zero, y1)
    assert np.max(np.abs(np.asarray(bwd.ys.R[-1] - free.y0.R))) < 1e-8
    assert np.max(np.abs(np.asarray(bwd.ys.x[-1] - free.y0.x))) < 1e-8


def test_vmap_over_scenes_matches_single(free):
    Omegas = jnp.array([[0.5, 1.0, -0.3], [1.0, -0.2, 0.4]])
    scenes = jax.vmap(lambda W: eqx.tree_at(lambda sc: sc.y0.x, free, W))(Omegas)
    run = lambda sc: s.simulate(sc, s.RKMK32(), t1=2.0, rtol=1e-7, saveat=3)
    batch = eqx.filter_vmap(run)(scenes)
    for i in range(2):
        one = run(eqx.tree_at(lambda sc: sc.y0.x, free, Omegas[i]))
        assert np.allclose(batch.R[i], one.R, atol=1e-13)


# --------------------------------------------------------------------------
# Against ambient diffrax on the seed scenario
# --------------------------------------------------------------------------


def _ambient_tsit5(scene, T, ts, tol):
    # The same equations, forgetting the group: R' = R hat(Omega), Rd' = Rd hat(Omega_d).
    def f(t, y, args):
        R, x = y
        tan = scene.vector_field(t, s.LieState(R, x))
        return R @ s.hat(tan.xi), tan.dx

    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(f),
        diffrax.Tsit5(),
        0.0,
        T,
        None,
        (scene.y0.R, scene.y0.x),
        stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
        saveat=diffrax.SaveAt(ts=ts),
        max_steps=100_000,
    )
    return sol.ys


@pytest.mark.parametrize(
    "method, bound",
    # RKMKTsit5's dense output is a cubic Hermite in the algebra (fourth order inside
    # a step, against RKMK45's quartic): 2e-8 at the save point inside the transient.
    [(s.RKMK45(), 1e-8), (s.RKMKTsit5(coords="cayley"), 5e-8)],
    ids=["RKMK45", "RKMKTsit5-cayley"],
)
def test_seed_agrees_with_ambient_tsit5(method, bound):
    scene = s.scenes.seed()
    T = s.scenes.SEED_DURATION
    ts = jnp.linspace(0.0, T, 21)
    tol = 1e-9
    tr = s.simulate(scene, method, t1=T, rtol=tol, atol=tol, saveat=ts)
    R_amb, x_amb = _ambient_tsit5(scene, T, ts, tol)
    # Both are ~1e-10 accurate at this tolerance (global error ~ tolerance).
    assert np.max(np.abs(np.asarray(tr.R - R_amb[:, 0]))) < bound
    assert np.max(np.abs(np.asarray(tr.Rd - R_amb[:, 1]))) < bound
    assert np.max(np.abs(np.asarray(tr.Omega - x_amb[:, :3]))) < bound
    assert np.max(np.asarray(s.orthogonality_error(tr.R))) <= 1e-13
    assert np.max(np.asarray(s.orthogonality_error(tr.Rd))) <= 1e-13
    assert tr.M.shape == (21, 3)


# --------------------------------------------------------------------------
# Gradients through the adaptive path
# --------------------------------------------------------------------------


def _free_cost(sc):
    tr = s.simulate(sc, s.RKMK32(), t1=0.5, rtol=1e-9, atol=1e-9, saveat=3)
    return jnp.sum(tr.R[-1] * jnp.arange(9.0).reshape(3, 3)) + jnp.sum(tr.Omega**2)


def test_default_derivatives_agree_in_every_mode(free):
    # Three programs for one derivative of the same discretised run (step sizes held
    # constant, as diffrax holds them), equal to round-off. Through all 30 floats of the
    # free body, reverse mode is diffrax's RecursiveCheckpointAdjoint (its backward pass
    # behind a linear_call) and forward mode diffrax.ForwardMode. Through the 3 start
    # rates both modes are the one-pass Jacobian (ForwardMode with the unit tangents
    # batched over one run), under vmap and in float32 too. Central differences of the
    # whole adaptive run (whose step sizes move with the rates) tend to it as tol -> 0.
    flat = lambda g: jnp.concatenate([jnp.ravel(x) for x in jax.tree.leaves(g)])
    rev = eqx.filter_jit(eqx.filter_grad(_free_cost))(free)
    fwd = eqx.filter_jit(jax.jacfwd(_free_cost))(free)
    assert flat(rev).size == 30 and np.all(np.abs(np.asarray(rev.y0.x)) > 1e-2)
    np.testing.assert_allclose(flat(fwd), flat(rev), rtol=1e-10, atol=1e-13)

    def rates(w, sc=free):
        return _free_cost(eqx.tree_at(lambda sc: sc.y0.x, sc, w))

    value_and_grad = jax.jit(jax.value_and_grad(rates))
    np.testing.assert_allclose(value_and_grad(free.y0.x)[1], rev.y0.x, rtol=1e-10)
    fd = []
    for i in range(3):
        dw = jnp.zeros(3).at[i].set(1e-5)
        fd.append((value_and_grad(free.y0.x + dw)[0] - value_and_grad(free.y0.x - dw)[0]) / 2e-5)
    np.testing.assert_allclose(fd, rev.y0.x, rtol=1e-6)
    # Under vmap the rule runs batched; two starts whose runs take different numbers of
    # steps (one lane takes empty steps after it is done).
    W = jnp.stack([free.y0.x, jnp.array([0.2, -0.4, 0.9])])
    Jb = jax.jit(jax.vmap(jax.jacfwd(rates)))(W)
    np.testing.assert_allclose(Jb[0], rev.y0.x, rtol=1e-10)
    np.testing.assert_allclose(Jb[1], value_and_grad(W[1])[1], rtol=1e-10)

    free32 = jax.tree.map(lambda x: x.astype(jnp.float32), free)
    g32 = jax.jit(jax.grad(rates))(free32.y0.x, free32)
    assert g32.dtype == jnp.float32
    np.testing.assert_allclose(g32, rev.y0.x, rtol=1e-4)


def test_second_derivatives(free):
    """``jax.hessian`` through the 3 start rates (the one-pass Jacobian, forward over
    forward) equals ``jacfwd`` of ``jacfwd`` through `diffrax.ForwardMode`, and so does
    reverse over forward (``jacrev`` of ``jacfwd``: the Jacobian program is a while loop,
    which JAX differentiates forward only, so its transpose runs by columns,
    `_engine.tangents.forward_differentiated`, so JAX's "Reverse-mode differentiation does not
    work for lax.while_loop" is never raised); through all 30 floats the default
    derivatives (a ``linear_call``) have first derivatives only, and a second one says
    which adjoint to pass (not a bare ``AssertionError``)."""

    def rates(w, adjoint=None):
        sc = eqx.tree_at(lambda sc: sc.y0.x, free, w)
        tr = s.simulate(sc, s.RKMK32(), t1=0.5, rtol=1e-9, atol=1e-9, saveat=3, adjoint=adjoint)
        return jnp.sum(tr.R[-1] * jnp.arange(9.0).reshape(3, 3)) + jnp.sum(tr.Omega**2)

    w = free.y0.x
    H = jax.jit(jax.hessian(rates))(w)
    ref = jax.jit(jax.jacfwd(jax.jacfwd(lambda w: rates(w, diffrax.ForwardMode()))))(w)
    assert np.abs(np.asarray(ref) - np.asarray(ref).T).max() < 1e-10 * np.abs(ref).max()
    np.testing.assert_allclose(H, ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())
    H_rf = jax.jit(jax.jacrev(jax.jacfwd(rates)))(w)
    np.testing.assert_allclose(H_rf, ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())
    with pytest.raises(NotImplementedError, match="DirectAdjoint"):
        jax.hessian(lambda sc: _free_cost(sc).sum())(free)


def test_dense_output_of_an_empty_step_has_finite_derivatives():
    # Under vmap a finished run keeps taking empty steps (t0 == t1) while the others go
    # on; their dense output is selected away, but 0/0 there made every reverse-mode
    # gradient of such a batch NaN (0 times NaN).
    from so3jax._integrators._diffrax import LieInterpolation

    def at(R0, cu, cx, t0, t1, t):
        return LieInterpolation(t0=t0, t1=t1, R0=R0, cu=cu, cx=cx).evaluate(t)

    Rs, cu, cx = jnp.asarray(R0)[None], jnp.full((2, 1, 3), 0.1), jnp.ones((3, 3))
    one = jnp.asarray(1.0)
    y = at(Rs, cu, cx, one, one, one)
    np.testing.assert_allclose(y.R, Rs, atol=1e-15)
    np.testing.assert_allclose(y.x, cx[-1])
    grads = jax.jit(
        jax.grad(lambda *a: jnp.sum(at(*a).R) + jnp.sum(at(*a).x), argnums=(0, 1, 2, 3, 4, 5))
    )
    for g in grads(Rs, cu, cx, one, one, one):
        assert np.all(np.isfinite(np.asarray(g)))


# --------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------


def test_bad_input(free):
    with pytest.raises(ValueError, match="embedded"):
        s.simulate(free, s.RKMK4(), t1=1.0, rtol=1e-6)
    with pytest.raises(ValueError, match="t1"):
        s.simulate(free, s.RKMK45(), rtol=1e-6)
    with pytest.raises(ValueError, match="rtol"):
        s.simulate(free, s.RKMK45(), t1=1.0, rtol=-1.0)
    with pytest.raises(ValueError, match="t1 must be greater"):
        s.simulate(free, s.RKMK45(), t1=0.0, rtol=1e-6)
    with pytest.raises(ValueError, match="saveat"):
        s.simulate(free, s.RKMK45(), t1=1.0, rtol=1e-6, saveat=jnp.array([0.0, 2.0]))
    with pytest.raises(ValueError, match="n_steps"):
        s.simulate(free, s.RKMK45(), t1=1.0, rtol=1e-6, n_steps=10)
    with pytest.raises(ValueError, match="dt and n_steps"):
        s.simulate(free, s.RKMK45())
    with pytest.raises(ValueError, match="method"):
        s.diffrax_solver("RKMK45")
    with pytest.raises(ValueError, match="scene"):
        s.lie_term(lambda t, y, a: y)
    with pytest.raises(ValueError, match="jump"):
        s.simulate(s.scenes.unwinding(hysteresis=True), s.RKMK45(), t1=1.0, rtol=1e-6)


def test_wrong_term_is_refused(free):
    solver = s.diffrax_solver(s.RKMK45())
    # A plain ODETerm is not a LieTerm: diffrax refuses the pairing.
    plain = diffrax.ODETerm(lambda t, y, args: y)
    with pytest.raises(ValueError, match="not compatible"):
        diffrax.diffeqsolve(plain, solver, 0.0, 1.0, 0.1, free.y0)
    # A LieTerm whose field returns the wrong thing gets a clear message.
    bad = s.LieTerm(lambda t, y, args: y)
    with pytest.raises(ValueError, match="LieTangent"):
        diffrax.diffeqsolve(bad, solver, 0.0, 1.0, 0.1, free.y0)
