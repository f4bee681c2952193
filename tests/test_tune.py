"""Tracking cost, its gradients, checkpointed memory and gradient-based tuning."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import so3jax as s
from so3jax._tune import with_gains

DT = 1e-2


def _seed_with(p, scene=None):
    """The seed scene with gains p[0], p[1] and inertia diag(J0) * p[2:5]."""
    scene = s.scenes.seed() if scene is None else scene
    sc = with_gains(scene, p[0], p[1])
    return eqx.tree_at(lambda c: c.body.inertia, sc, scene.body.inertia * p[2:5])


def _central_fd(f, p, rel=1e-5):
    p = np.asarray(p, dtype=np.float64)
    g = np.zeros_like(p)
    for i in range(p.size):
        h = rel * max(abs(p[i]), 1.0)
        e = np.zeros_like(p)
        e[i] = h
        g[i] = (float(f(p + e)) - float(f(p - e))) / (2 * h)
    return g


P0 = np.array([3.0, 1.5, 1.0, 1.0, 1.0])  # k_R, k_Omega, inertia scales


def test_rollout_cost_equals_tracking_cost_of_simulate():
    sc = with_gains(s.scenes.seed(), 3.0, 1.5)
    for n, save_every, cks in ((50, 1, ("auto", None)), (60, 3, (7,))):
        traj = s.simulate(sc, s.RKMK4(), DT, n, save_every)
        ref = float(s.tracking_cost(traj, sc))
        for ck in cks:
            c = float(
                s.rollout_cost(sc, s.RKMK4(), DT, n, save_every=save_every, checkpoint_every=ck)
            )
            assert c == pytest.approx(ref, rel=1e-13, abs=0)
    # An independent quadrature: the trapezoid rule written out on the saved points.
    traj = s.simulate(sc, s.RKMK4(), DT, 50)
    psi = np.asarray(s.attitude_error_function(traj.R, traj.Rd))
    Od = np.stack([np.asarray(sc.reference(t)[0]) for t in np.asarray(traj.t)])
    R, Rd, W, M = (np.asarray(a) for a in (traj.R, traj.Rd, traj.Omega, traj.M))
    eW = W - np.einsum("nji,njk,nk->ni", R, Rd, Od)
    w = s.CostWeights()
    f = float(w.psi) * psi + float(w.omega) * (eW**2).sum(-1) + float(w.effort) * (M**2).sum(-1)
    assert float(s.tracking_cost(traj, sc)) == pytest.approx(np.trapezoid(f, traj.t), rel=1e-12)


def test_hessian_of_the_carried_sum_is_one_loop():
    """`rollout_cost` adds whole trapezoids in its carry, so the cost is linear in the
    final carry: ``jax.hessian`` needs the ``jvp`` of the Jacobian program and no value of
    it beside (one loop in the lowered program, where the last point's integrand taken
    after the loop made two), and it equals autodiff's."""
    R0, W0 = s.initial_states(jax.random.PRNGKey(2), 16)

    def cost(k, program="auto"):
        sc = s.scenes.seed()
        return s.expected_cost(sc, k[0], k[1], R0, W0, s.LieEuler(), DT, 20, program=program)

    k = jnp.array([3.0, 1.5])
    H = jax.jit(jax.hessian(cost))
    assert H.lower(k).as_text().count("stablehlo.while") == 1
    ref = jax.jit(jax.hessian(lambda k: cost(k, "autodiff")))(k)
    np.testing.assert_allclose(H(k), ref, rtol=1e-10)


def test_tracking_cost_of_a_batch_of_trajectories():
    """Leading batch axes (the trapezoid rule's weights per run): each run's cost, and
    ``vmap`` of the cost inside (where the runs share their times) the same."""
    sc = with_gains(s.scenes.seed(), 3.0, 1.5)
    R0, W0 = s.initial_states(jax.random.PRNGKey(4), 3)
    run = lambda R, W: s.simulate(sc, s.RKMK4(), DT, 40, R0=R, Omega0=W)  # noqa: E731
    trajs = jax.vmap(run)(R0, W0)
    assert trajs.t.shape == (3, 41)
    each = [float(s.tracking_cost(run(R0[i], W0[i]), sc)) for i in range(3)]
    np.testing.assert_allclose(s.tracking_cost(trajs, sc), each, rtol=1e-13)
    inside = jax.vmap(lambda R, W: s.tracking_cost(run(R, W), sc))(R0, W0)
    np.testing.assert_allclose(inside, each, rtol=1e-13)


@pytest.mark.parametrize("integrator", ["RKMK4", "ambient-rk4"])
def test_gradient_matches_central_differences(integrator):
    """d cost / d (k_R, k_Omega, inertia) against central differences, float64, 1e-6 relative."""
    n = 100

    def cost(p):
        sc = _seed_with(p)
        if integrator == "RKMK4":
            traj = s.simulate(sc, s.RKMK4(), DT, n)
        else:
            traj = s.simulate_ambient(sc, "rk4", dt=DT, n_steps=n)
        return s.tracking_cost(traj, sc)

    p = jnp.asarray(P0)
    value_and_grad = jax.jit(jax.value_and_grad(cost))
    g = np.asarray(value_and_grad(p)[1])
    fd = _central_fd(lambda q: value_and_grad(q)[0], P0)  # one compilation less
    assert np.all(np.abs(g) > 1e-4)  # every parameter matters
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_checkpointed_reverse_pass_is_sublinear_in_memory_and_exact():
    """Temp memory of the gradient: ~sqrt(n) with checkpointing, ~n without."""
    scene = s.scenes.seed()
    method = s.LieEuler()  # the memory structure does not depend on the method; cheap to compile
    k = jnp.array([3.0, 1.5])

    def grad_fn(n, ck, program="autodiff"):
        f = lambda k: s.rollout_cost(
            with_gains(scene, k[0], k[1]), method, DT, n, checkpoint_every=ck, program=program
        )
        return jax.jit(jax.grad(f))

    def temp(n, ck):
        return grad_fn(n, ck).lower(k).compile().memory_analysis().temp_size_in_bytes

    small, big = 400, 6400
    ck_small, ck_big, plain_big = temp(small, "auto"), temp(big, "auto"), temp(big, None)
    # 16x the horizon: sqrt -> ~4x (measured 5.9x to 6.0x: XLA's buffers are not
    # exactly proportional); linear (no checkpoints) -> ~16x.
    assert ck_big / ck_small < 8
    assert plain_big / ck_small > 10
    assert ck_big < plain_big / 8
    # The default reverse pass (two gains: the Jacobian's columns from the tangent
    # program) stores no residuals, and the cost's integral is summed in its carry:
    # it saves nothing per step, so its memory does not grow with the horizon
    # (measured: the same bytes at both; plain autodiff stores 176 numbers a step).
    dflt = [
        grad_fn(n, "auto", "auto").lower(k).compile().memory_analysis().temp_size_in_bytes
        for n in (small, big)
    ]
    assert (dflt[1] - dflt[0]) / (big - small) < 1  # under a byte a step
    assert dflt[1] < ck_small
    # The checkpointed reverse pass gives the forward-mode derivative.
    g_ck = np.asarray(grad_fn(small, "auto")(k))
    f = lambda k: s.rollout_cost(with_gains(scene, k[0], k[1]), method, DT, small)
    np.testing.assert_allclose(g_ck, np.asarray(jax.jit(jax.jacfwd(f))(k)), rtol=1e-11)


def test_tune_lowers_cost_and_lands_near_the_best_grid_point():
    scene = s.scenes.seed()
    n = 300  # 3 s at dt = 1e-2
    key = jax.random.key(0)
    R0, _ = s.initial_states(key, 2)
    # Forward mode (2 gains) compiles in a third of the time of reverse mode;
    # test_forward_and_reverse_tuning_agree checks the two give the same steps.
    res = s.tune(
        scene,
        (1.0, 1.0),
        dt=DT,
        n_steps=n,
        R0=R0,
        n_iter=100,
        learning_rate=0.1,
        gradient="forward",
    )
    assert res.cost < 0.8 * res.initial_cost
    assert res.cost_history.shape == (101,)
    assert res.k_R_history.shape == (101,)
    assert res.cost == pytest.approx(res.cost_history[res.best_iteration])
    # A fine grid over the same cost, vmapped: the sweep's mean cost per gain pair.
    grid = s.sweep(
        scene,
        np.geomspace(1.0, 60.0, 25),
        np.geomspace(0.3, 20.0, 25),
        key=key,
        n_attitudes=2,
        dt=DT,
        n_steps=n,
        chunk_size=1250,
        progress=False,
        scalarize=False,  # same numbers (test_sweep checks it), compiles faster
    )
    best = grid.best()
    assert 0 < best < 624 and np.isfinite(grid.mean_cost[best])
    assert res.cost <= 1.05 * grid.mean_cost[best]


def test_forward_and_reverse_tuning_agree():
    scene = s.scenes.seed()
    # Lie-Euler: the cheapest method to compile; the tuning code is the same.
    kw = dict(method=s.LieEuler(), dt=DT, n_steps=40, n_iter=3, per_axis=True)
    rev = s.tune(scene, (2.0, 1.0), gradient="reverse", **kw)
    fwd = s.tune(scene, (2.0, 1.0), gradient="forward", **kw)
    assert rev.k_R_history.shape == (4, 3)
    np.testing.assert_allclose(rev.cost_history, fwd.cost_history, rtol=1e-10)
    np.testing.assert_allclose(rev.k_Omega_history, fwd.k_Omega_history, rtol=1e-10)


def test_tune_compiles_its_iteration_with_the_engines_options(monkeypatch):
    """`tune`'s iteration goes through `so3jax._tune.jit_own`: the engine's options for the
    library's own programs reach XLA (one XLA does not know is rejected, and the program
    compiles with XLA's defaults), a level the caller names in ``XLA_FLAGS`` wins, and the
    tuning does not depend on the level."""
    from so3jax import _engine, _tune

    scene = s.scenes.seed()
    kw = dict(method=s.LieEuler(), dt=DT, n_steps=20, n_iter=3)
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")
    assert _tune.own_compiler_options() is None
    caller = s.tune(scene, (2.0, 1.0), **kw)
    monkeypatch.setenv("XLA_FLAGS", "")
    level2 = {jax.default_backend(): {"xla_backend_optimization_level": 2}}
    with _engine.policy.using(own_compiler_options=level2):
        assert _tune.own_compiler_options() == {"xla_backend_optimization_level": 2}
        own = s.tune(scene, (2.0, 1.0), **kw)
    np.testing.assert_allclose(own.cost_history, caller.cost_history, rtol=1e-10)
    np.testing.assert_allclose(own.k_R_history, caller.k_R_history, rtol=1e-10)
    # An option XLA does not know reaches it and is rejected: the iteration then compiles
    # with XLA's defaults, with a warning, and tunes the same.
    unknown = {jax.default_backend(): {"xla_no_such_option": 1}}
    with _engine.policy.using(own_compiler_options=unknown):
        with pytest.warns(UserWarning, match="xla_no_such_option"):
            rejected = s.tune(scene, (2.0, 1.0), **kw)
    np.testing.assert_allclose(rejected.cost_history, caller.cost_history, rtol=1e-10)


def test_auto_gradient_is_forward_mode_through_few_scalars():
    """``gradient="auto"`` (the default) runs forward mode through at most
    `FORWARD_MODE_MAX` tuned scalars and reverse mode beyond, in both modes of `tune`;
    the result says which (`TuneResult.gradient`)."""
    from so3jax import _tune

    assert _tune._resolve_gradient("auto", (1.0, 2.0)) == "forward"
    assert _tune._resolve_gradient("auto", jnp.zeros(_tune.FORWARD_MODE_MAX)) == "forward"
    assert _tune._resolve_gradient("auto", [jnp.zeros(_tune.FORWARD_MODE_MAX), 1.0]) == "reverse"
    assert _tune._resolve_gradient("reverse", 1.0) == "reverse"
    with pytest.raises(ValueError, match="auto"):
        _tune._resolve_gradient("backward", 1.0)
    scene = s.scenes.seed()
    kw = dict(method=s.LieEuler(), dt=DT, n_steps=4, n_iter=0)  # nothing is differentiated

    def cost(tr):
        return jnp.sum(tr.Omega**2)

    def every_float(sc):  # the seed's 46 scalars
        return sc.y0, sc.body, sc.controller.gains, sc.reference

    modes = [
        s.tune(scene, (2.0, 1.0), **kw).gradient,
        s.tune(scene, (2.0, 1.0), gradient="reverse", **kw).gradient,
        s.tune(scene, cost=cost, **kw).gradient,
        s.tune(scene, cost=cost, where=every_float, **kw).gradient,
    ]
    assert modes == ["forward", "reverse", "forward", "reverse"]


def test_bad_input():
    scene = s.scenes.seed()
    with pytest.raises(ValueError, match="effort"):
        s.CostWeights(effort=-1.0)
    free = s.scenes.free_body(jnp.array([1.0, 2.0, 3.0]), jnp.eye(3), jnp.ones(3))
    with pytest.raises(ValueError, match="Rd and M"):
        s.tracking_cost(s.simulate(free, s.LieEuler(), DT, 2), scene)
    with pytest.raises(ValueError, match="gradient"):
        s.tune(scene, gradient="sideways")
    with pytest.raises(ValueError, match="gains0"):
        s.tune(scene, (1.0, -1.0))
    with pytest.raises(ValueError, match="geometric controller"):
        s.tune(s.scenes.unwinding())
    with pytest.raises(ValueError, match="checkpoint_every"):
        s.rollout_cost(scene, s.RKMK4(), DT, 10, checkpoint_every=0)


def test_unmoved_saved_points_carry_symbolic_zero_tangents():
    """A gain moves the body, not its reference: the saved ``Rd`` reaches a cost with a
    symbolic zero tangent (the engine makes no zeros to batch, mask and multiply, which
    would take XLA temp memory), while ``R`` carries a real one: ``jacfwd`` of one run
    (array program), ``grad`` of 16 (scalarized)."""
    from functools import partial

    from jax.custom_derivatives import SymbolicZero

    seen = []

    @jax.custom_jvp
    def probe(R, Rd):
        return jnp.sum(R) + jnp.sum(Rd)

    @partial(probe.defjvp, symbolic_zeros=True)
    def _probe_jvp(primals, tangents):
        seen.append(tuple(isinstance(t, SymbolicZero) for t in tangents))
        tR = tangents[0] if not isinstance(tangents[0], SymbolicZero) else 0.0
        return probe(*primals), jnp.sum(tR)

    scene = s.scenes.seed()
    R0, W0 = s.initial_states(jax.random.key(2), 16)

    def one(k, R, W):
        tr = s.simulate(with_gains(scene, k[0], k[1]), s.RKMK4(), 1e-2, 20, R0=R, Omega0=W)
        return probe(tr.R, tr.Rd)

    k = jnp.array([8.81, 2.54])
    single = lambda k: one(k, R0[0], W0[0])  # noqa: E731
    batch = lambda k: jnp.mean(jax.vmap(one, (None, 0, 0))(k, R0, W0))  # noqa: E731
    for cost, d in ((single, jax.jacfwd), (batch, jax.grad)):
        seen.clear()
        g = jax.jit(d(cost))(k)
        assert seen and set(seen) == {(False, True)}, (d.__name__, seen)
        assert np.all(np.isfinite(g)) and np.any(g != 0)
