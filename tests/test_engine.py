"""The execution engine (`so3jax._engine`): one program per transform, same numbers.

References are independent of the engine's own derivative programs: JAX's
autodiff of the plain array program (``program="autodiff"``), central finite
differences, and Python loops over single runs.
"""

import functools
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import so3jax as s
from so3jax import _engine
from so3jax._engine.passes import cuts, scalarize as sc
from so3jax._simulate import _simulate
from so3jax._tune import _check_weights, _rollout, with_gains, with_initial_state, with_start

N, DT = 12, 0.05


def _seed(dtype=jnp.float64):
    sc = s.scenes.seed()
    if dtype != jnp.float64:
        sc = jax.tree.map(
            lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, sc
        )
    return sc


def _traj_cost(program, method, save_every=1, dtype=jnp.float64):
    """A user's cost on the saved points of a run, as a function of the two gains."""
    sc0 = _seed(dtype)

    def cost(k):
        sc = with_gains(sc0, k[0], k[1])
        dt = jnp.asarray(DT, dtype)
        tr = _simulate(
            sc, method, dt, jnp.asarray(0.0, dtype), N // save_every, save_every, program
        )
        return jnp.sum(tr.Omega**2) + jnp.sum(jnp.sin(tr.M)) + jnp.sum(tr.R[-1] * tr.Rd[-1])

    return cost


def _rollout_cost(program, method):
    sc0 = _seed()
    w = _check_weights(None)

    def cost(k):
        sc = with_gains(sc0, k[0], k[1])
        return _rollout(sc, method, jnp.asarray(DT), jnp.asarray(0.0), w, N, 1, 4, program)

    return cost


def _jit_grad(f):
    """``jit(grad(f))``: one compiled program (eager ``grad`` of a run compiles its
    pieces one by one, 10 to 25 % slower to build)."""
    return jax.jit(jax.grad(f))


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


K0 = jnp.array([3.0, 1.5])

METHODS = [
    s.RKMK4(),
    s.RKMK4(coords="cayley"),
    s.CF4(),
    s.CG3(),
    s.LGVI(),
    s.RKMK45(),
]


#: Saved points of the free-body runs.
FB_SAVES = 7


def _free_body_cost(program, method):
    """A cost of a free body's run in its step size (a parameter) and its initial rates
    (a carry leaf). The engine sees 7 differentiated scalars (the rates reach it twice: in
    the scene and in the carry), so the default gradient is the one-pass Jacobian."""
    R0 = s.from_axis_angle(jnp.array([0.3, -0.5, 0.8]), 1.1)
    J = jnp.diag(jnp.array([1.0, 2.0, 2.5]))

    def cost(x):
        sc = s.scenes.free_body(J.astype(x.dtype), R0.astype(x.dtype), x[1:])
        tr = _simulate(sc, method, x[0], jnp.asarray(0.0, x.dtype), FB_SAVES, 2, program)
        return jnp.sum(tr.Omega**2) + jnp.sum(tr.R[-1] * R0.astype(x.dtype))

    return cost


X0 = jnp.array([DT, 0.4, -0.2, 0.9])

#: Methods whose discrete adjoint is checked: RKMK, commutator-free, variational.
ADJOINT_CHECKED = (type(s.RKMK4()), type(s.CF4()), type(s.LGVI()))


@pytest.mark.parametrize("method", METHODS, ids=lambda m: f"{m.name}-{getattr(m, 'coords', '')}")
def test_gradients_equal_autodiff(method):
    """The default gradient (the one-pass Jacobian through the step size and the initial
    rates) against JAX's autodiff, every method, exp and Cayley; the discrete
    adjoint for one method of each family (the others share its code: the suite's time
    goes to compiling these programs). The reference is JAX's forward mode (``jacfwd``
    of the checkpointed array program), which compiles in less than half the time of
    its reverse mode (RKMK45: 4.5 against 10.2 s); reverse-mode autodiff is the
    reference of the seed tests below."""
    ref = jax.jit(jax.jacfwd(_free_body_cost("autodiff", method)))(X0)
    assert _rel(_jit_grad(_free_body_cost("auto", method))(X0), ref) < 1e-10
    (chosen,) = s.explain(jax.grad(_free_body_cost("auto", method)), X0).of("derivative")
    limit = _engine.policy.current().forward_jacobian_max
    assert chosen["strategy"] == "one-pass Jacobian" and 4 <= chosen["scalars"] <= limit
    if type(method) in ADJOINT_CHECKED and getattr(method, "coords", "exp") == "exp":
        assert _rel(_jit_grad(_free_body_cost("adjoint", method))(X0), ref) < 1e-10


# The seed-scene tests use the one-stage method: the controller, reference and cost are
# the same, and the programs compile in a fraction of the time (the methods are covered
# on the free body above).
SEED_METHOD = s.LieEuler()


def test_adjoint_on_the_seed():
    """The seed (gains, controller, reference): ``program="adjoint"``'s discrete adjoint in
    reverse mode, and its forward mode, equal autodiff."""
    ref = _jit_grad(_traj_cost("autodiff", SEED_METHOD))(K0)
    assert _rel(_jit_grad(_traj_cost("adjoint", SEED_METHOD))(K0), ref) < 1e-10
    assert _rel(jax.jit(jax.jacfwd(_traj_cost("adjoint", SEED_METHOD)))(K0), ref) < 1e-10


def test_adjoint_from_residuals():
    """The discrete adjoint from every step's residuals (within the policy's
    ``adjoint_residual_bytes``) equals autodiff, saving every third step (blocks of steps
    between saved points; `tune`'s test saves every step), for one run, under ``vmap`` and
    in float32; the plan names what was saved. Past the budget the residuals are dropped
    for checkpoints (which `test_adjoint_on_the_seed` checks)."""
    Ks = jnp.stack([K0, 1.3 * K0])
    f = _traj_cost("adjoint", SEED_METHOD, save_every=3)
    ref = _traj_cost("autodiff", SEED_METHOD, save_every=3)
    with _engine.policy.using(adjoint_residual_bytes=2**62):
        assert _rel(_jit_grad(f)(K0), _jit_grad(ref)(K0)) < 1e-10
        (entry,) = s.explain(jax.grad(f), K0).of("adjoint")
        assert entry["saved"] == "residuals" and entry["steps"] == N
        batched = jax.jit(jax.vmap(jax.grad(f)))(Ks)
        assert _rel(batched, jax.jit(jax.vmap(jax.grad(ref)))(Ks)) < 1e-10
        f32 = _traj_cost("adjoint", SEED_METHOD, save_every=3, dtype=jnp.float32)
        g32 = _jit_grad(f32)(K0.astype(jnp.float32))
        assert g32.dtype == jnp.float32 and _rel(g32, _jit_grad(ref)(K0)) < 1e-4
    with _engine.policy.using(adjoint_residual_bytes=entry["bytes_per_step"] * N - 1):
        (entry,) = s.explain(jax.grad(f), K0).of("adjoint")
    assert entry["saved"] == "checkpoints"


@pytest.mark.parametrize("program", ["auto"])
def test_gradients_match_finite_differences(program):
    f = _traj_cost(program, SEED_METHOD, save_every=3)
    g = jax.grad(f)(K0)
    h = 1e-6
    fd = [(f(K0.at[i].add(h)) - f(K0.at[i].add(-h))) / (2 * h) for i in range(2)]
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_hessian_on_the_seed():
    """``jax.hessian`` in the two gains (a Newton step's matrix) of a user's cost on the
    saved points equals JAX's autodiff of the array program and central differences of
    the gradient; float32 follows float64. (`rollout_cost` runs the same rule; batches
    of runs are `test_second_derivatives_equal_autodiff`'s.)"""
    cost = _traj_cost("auto", SEED_METHOD)
    H = jax.jit(jax.hessian(cost))(K0)
    assert _rel(H, jax.jit(jax.hessian(_traj_cost("autodiff", SEED_METHOD)))(K0)) < 1e-10
    g, h = _jit_grad(cost), 1e-5
    fd = np.stack([(g(K0.at[i].add(h)) - g(K0.at[i].add(-h))) / (2 * h) for i in range(2)])
    assert np.abs(H[0, 1]) > 1e-3 * np.abs(H).max()  # the gains interact
    np.testing.assert_allclose(H, fd.T, rtol=1e-6, atol=1e-8 * np.abs(H).max())
    H32 = jax.jit(jax.hessian(_traj_cost("auto", SEED_METHOD, dtype=jnp.float32)))(
        K0.astype(jnp.float32)
    )
    assert H32.dtype == jnp.float32 and _rel(H32, H) < 1e-4


@pytest.mark.parametrize("program", ["adjoint"])
def test_rollout_cost_gradient(program):
    ref = _jit_grad(_rollout_cost("autodiff", SEED_METHOD))(K0)
    assert _rel(_jit_grad(_rollout_cost(program, SEED_METHOD))(K0), ref) < 1e-10


def test_float32_gradients():
    f64 = jax.jit(jax.jacfwd(_free_body_cost("autodiff", s.CF4())))(X0)
    for program in ("adjoint", "auto"):  # "auto": the one-pass Jacobian
        x = X0.astype(jnp.float32)
        g = _jit_grad(_free_body_cost(program, s.CF4()))(x)
        assert g.dtype == jnp.float32
        assert _rel(g, f64) < 1e-4


def test_batched_equals_loop_and_single():
    """vmap equals a loop of single runs, in either layout."""
    sc0 = _seed()
    R0 = s.random_rotation(jax.random.PRNGKey(1), (3,))

    def final(R, program="auto"):
        sc = with_initial_state(sc0, R, jnp.array([0.1, -0.2, 0.3]))
        tr = _simulate(sc, SEED_METHOD, jnp.asarray(DT), jnp.asarray(0.0), N // 2, 2, program)
        return tr.R, tr.M

    batched = jax.jit(jax.vmap(final))(R0)
    loop = [final(R) for R in R0]
    for b, ls in zip(batched, zip(*loop, strict=True), strict=True):
        np.testing.assert_allclose(b, np.stack(ls), rtol=0, atol=1e-13)
    # A batch this small runs the array program, vmapped: bit for bit program="array".
    arr = jax.jit(jax.vmap(lambda R: final(R, "array")))(R0)
    np.testing.assert_array_equal(batched[0], arr[0])
    scal = jax.vmap(lambda R: final(R, "scalar"))(R0)  # the scalarized program agrees
    np.testing.assert_allclose(scal[0], batched[0], rtol=0, atol=1e-13)


#: A closed-over constant: batching turns it into a const of linear_call's callee
#: (which linear_call evaluates without consts unless the rule hoists them).
_W = np.array([1.0, 2.0, 3.0])


def _toy(P, program, K=None, n=21, every=3):
    """A small nonlinear loop with an integer counter in its carry."""
    step = lambda P, c: (c[0] + 0.1 * jnp.sin(P * c[0] * _W) + 0.01 * P**2, c[1] + 1)
    observe = lambda P, c: jnp.sum(_W * c[0] ** 2)
    c0 = (jnp.array([0.1, 0.4, -0.3]), jnp.array(0, jnp.int32))
    ys, cN = _engine.run(step, observe, P, c0, n, every, checkpoint=K, program=program)
    return jnp.sum(ys) + jnp.sum(jnp.cos(cN[0]))


def test_checkpointed_jvp_starts_settled_carry_tangents():
    """JAX's ``jvp`` of the checkpointed program (`_engine.derivatives.Autodiff`) starts the
    carry leaves that a step makes nonzero with zero tangents (the ``"settle"`` pass), so
    that JAX differentiates each of the three nested loops (segments, saved points, steps)
    once, where its own fixed point takes two passes over a loop whose carry tangents start
    as symbolic zeros, each differentiating the loops inside it again. The plan says so;
    the gradient is the same with the pass off and with every pass off."""
    with _engine.policy.using(passes=frozenset()):
        ref = jax.grad(_toy)(1.7, "autodiff")
    for passes in (_engine.policy.PASSES, _engine.policy.PASSES - {"settle"}):
        with _engine.policy.using(passes=passes):
            plan = s.explain(jax.grad(_toy), 1.7, program="array")
            g = jax.grad(_toy)(1.7, "array")
        settled = [e for e in plan.of("settle") if e["what"] == "carry tangents"]
        # the carry's one float leaf (the counter has no tangent)
        assert settled == (
            [{"kind": "settle", "what": "carry tangents", "leaves": 1}]
            if "settle" in passes
            else []
        ), plan
        assert _rel(g, ref) < 1e-12


def test_vmap_of_grad_equals_loop_of_grads():
    """The batching rule for linear_call: vmap(grad) and jacfwd through the discrete adjoint."""
    ps = jnp.array([1.7, -0.4, 2.5])
    loop = np.stack([jax.grad(_toy)(p, "autodiff") for p in ps])
    for program in ("auto", "adjoint"):
        assert _rel(jax.vmap(jax.grad(_toy), in_axes=(0, None))(ps, program), loop) < 1e-12
        summed = jax.grad(lambda ps: jnp.sum(jax.vmap(lambda p: _toy(p, program))(ps)))(ps)
        assert _rel(summed, loop) < 1e-12
        jac = jax.jit(jax.jacfwd(lambda ps: jax.vmap(lambda p: _toy(p, program))(ps)))(ps)
        assert _rel(np.diag(jac), loop) < 1e-12


@functools.partial(jax.jit, static_argnums=1)
def _toy_times(P, program):
    """`_toy` through 9 scalars, jitted, with an observation that no input moves (a time)
    joined to a value that the inputs move, as `so3jax.simulate` joins ``t0`` and its times."""

    def step(P, c):
        dx = jnp.sin(P[:3] * c[0] * _W) + 0.1 * P[3:6] ** 2 + 0.01 * P[6:]
        return (c[0] + 0.1 * dx, c[1] + 1)

    def observe(P, c):
        return jnp.sum(_W * c[0] ** 2), 0.5 * c[1]

    c0 = (jnp.array([0.1, 0.4, -0.3]), jnp.array(0, jnp.int32))
    (ys, ts), cN = _engine.run(step, observe, P, c0, 21, 3, program=program)
    ts = jnp.concatenate([0 * P[:1], ts])
    return jnp.sum(ys) + jnp.sum(jnp.cos(cN[0])) + jnp.sum(ts * P[0])


def test_derivatives_of_a_jitted_batch_through_more_than_8_scalars():
    """``vmap`` batches a jitted run's jaxpr, the ``custom_jvp`` function alone; ``jvp``
    then runs the rule on the batched program. The rule through more than
    ``forward_jacobian_max`` scalars (JAX's ``jvp`` of the checkpointed program) must
    batch its outputs as the function does: it did not batch the times, and ``jacfwd``
    and ``grad`` of such a batch (the quadrotor's 12 gains) raised "Cannot concatenate
    arrays with different numbers of dimensions"."""
    ps = jnp.stack([jnp.linspace(0.5, 1.5, 9), jnp.linspace(1.2, 0.3, 9)])

    def mean(program):
        return lambda k: jnp.mean(jax.vmap(lambda p: _toy_times(p * k, program))(ps))

    k = jnp.ones(9)
    ref = jax.grad(mean("autodiff"))(k)
    assert np.all(np.isfinite(ref)) and np.abs(ref).min() > 0
    for program in ("auto", "array"):
        assert _rel(jax.jacfwd(mean(program))(k), ref) < 1e-12, program
        assert _rel(jax.grad(mean(program))(k), ref) < 1e-12, program


def _toy_second(P, program, jit):
    """A toy run through ``P`` (2 scalars: the one-pass Jacobian; 10: JAX's ``jvp``),
    with a time-like observation joined to a moved value, as `so3jax.simulate` joins
    its start to the saved points."""

    def step(P, c):
        dx = jnp.sin(P[0] * c[0] * _W) + 0.1 * P[1] ** 2 + 0.01 * jnp.sum(P[2:])
        return (c[0] + 0.1 * dx, c[1] + 1)

    def observe(P, c):
        return jnp.sum(_W * c[0] ** 2), 0.5 * c[1]

    c0 = (jnp.array([0.1, 0.4, -0.3]), jnp.array(0, jnp.int32))
    r = lambda P: _engine.run(step, observe, P, c0, 9, 3, program=program)  # noqa: E731
    (ys, ts), cN = (jax.jit(r) if jit else r)(P)
    ts = jnp.concatenate([0 * P[:1], ts])
    return jnp.sum(ys**2) + jnp.sum(jnp.cos(cN[0])) + jnp.sum(ts * P[0])


@pytest.mark.parametrize("n", [2, 10])
def test_second_derivatives_equal_autodiff(n):
    """``jax.hessian`` and the other second (and third) derivatives of runs, jitted or
    not, single or batched (3 runs: the array layout; 40: scalarized), equal JAX's
    autodiff of the checkpointed array program. The engine's rules run their programs
    on primals, and differentiating them again must not raise ("Custom JVP rule must
    produce primal and tangent outputs with corresponding shapes", "Linearization
    failed to produce known values", or "Cannot concatenate" under a jitted batch).
    ``jacfwd`` of ``jacfwd`` and ``jvp`` of ``jacfwd`` of a jitted run break when the
    ``linear_call`` batching rule batches every output under a ``vmap`` nothing in the
    call depends on (docs/engine.md, "Second derivatives"). Through few scalars the plan
    of a batch's Hessian differentiates its one-pass Jacobian program scalarized
    (`_engine.layout._dual_jvp`): from 40 runs its ``jvp`` too, at 20 only the Jacobian."""
    p = jnp.linspace(1.3, 0.7, n)
    u = jnp.linspace(-1.0, 1.0, n)

    def mean(program, jit, ps):
        one = lambda q: _toy_second(q, program, jit)  # noqa: E731
        return lambda k: jnp.mean(jax.vmap(lambda q: one(q * k))(ps))

    def jvp(f, t):
        return lambda q: jax.jvp(f, (q,), (t,))[1]

    def cases(program):
        f = lambda q: _toy_second(q, program, False)  # noqa: E731
        fj = lambda q: _toy_second(q, program, True)  # noqa: E731
        ps = p * jnp.linspace(0.8, 1.2, 3)[:, None]
        big = mean(program, True, p * jnp.linspace(0.8, 1.2, 40)[:, None])
        mid = mean(program, True, p * jnp.linspace(0.8, 1.2, 20)[:, None])
        assert (
            dict(_engine.policy.DEFAULT.batched_layout)["jacobian"][0]
            <= 20
            < dict(_engine.policy.DEFAULT.batched_layout)["jvp"][0]
        )
        J = jax.jit  # one compiled program per case (eager ones compile piece by piece)
        out = {"hessian(mean jitted vmap 40)": J(jax.hessian(big))(jnp.ones(n))}
        if n > _engine.policy.current().forward_jacobian_max:
            return out  # JAX's own jvp there: one case guards the composition
        if program == "auto":
            for batch, runs, jvp_layout in ((big, 40, "scalarized"), (mid, 20, "array")):
                # Every Jacobian program of the batch (the gradient's, and in the Hessian's
                # rule its value's) runs scalarized, and its jvp as `batched_layout` says.
                plan = s.explain(jax.hessian(batch), jnp.ones(n))
                layouts = {
                    (e["program"], e["layout"])
                    for e in plan.of("layout")
                    if e["runs"] == runs and e["program"] in ("jacobian", "jvp")
                }
                assert layouts == {("jacobian", "scalarized"), ("jvp", jvp_layout)}, plan
        return out | {
            # The value of `_dual_jvp` (the gradient beside its jvp) and third derivatives
            # through it, scalarized.
            "jvp(grad(mean jitted vmap 40)), value and tangent": jnp.stack(
                J(lambda k: jax.jvp(jax.grad(big), (k,), (u,)))(jnp.ones(n))
            ),
            "jacfwd(hessian(mean jitted vmap 40))": J(jax.jacfwd(jax.hessian(big)))(jnp.ones(n)),
            "jacrev(jacrev(mean jitted vmap 40))": J(jax.jacrev(jax.jacrev(big)))(jnp.ones(n)),
            # 20 runs: the Jacobian program scalarized, its jvp (batched_layout["jvp"]) not
            "hessian(mean jitted vmap 20)": J(jax.hessian(mid))(jnp.ones(n)),
            "hessian": J(jax.hessian(f))(p),
            "jacrev(jacrev)": J(jax.jacrev(jax.jacrev(f)))(p),
            "jvp(grad)": J(jvp(jax.grad(f), u))(p),
            "jacfwd^3": J(jax.jacfwd(jax.jacfwd(jax.jacfwd(f))))(p),
            "jvp(jvp(jacfwd))": J(jvp(jvp(jax.jacfwd(f), u), -u))(p),
            "jacfwd(jacfwd), jitted": J(jax.jacfwd(jax.jacfwd(fj)))(p),
            "jvp(jacfwd), jitted": J(jvp(jax.jacfwd(fj), u))(p),
            "vmap(hessian), jitted": J(jax.vmap(jax.hessian(fj)))(ps),
            "jvp(grad(mean jitted vmap 3))": J(jvp(jax.grad(mean(program, True, ps)), u))(
                jnp.ones(n)
            ),
        }

    ref, got = cases("autodiff"), cases("auto")
    for name in ref:
        assert np.abs(ref[name]).max() > 0, name
        assert _rel(got[name], ref[name]) < 1e-12, name


def test_second_derivatives_start_settled_carry_tangents():
    """``jax.hessian`` over a scalarized batch (40 runs) differentiates the one-pass
    Jacobian program, whose carry tangents start as symbolic zeros: JAX's fixed point
    differentiates the loop of saved points twice, and the step loop inside it on each
    pass, in the array and the scalarized program alike. The ``"settle"`` pass
    (`jacobian_tangents`) starts them with zeros in `_dual_jvp`: each loop once. The plan
    says so; the Hessian is the same with the pass off."""
    ps = jnp.linspace(1.3, 0.7, 2) * jnp.linspace(0.8, 1.2, 40)[:, None]

    def mean(program):
        return lambda k: jnp.mean(jax.vmap(lambda q: _toy_second(q * k, program, True))(ps))

    with _engine.policy.using(passes=frozenset()):
        ref = jax.hessian(mean("autodiff"))(jnp.ones(2))
    for passes in (_engine.policy.PASSES, _engine.policy.PASSES - {"settle"}):
        with _engine.policy.using(passes=passes):
            plan = s.explain(jax.hessian(mean("auto")), jnp.ones(2))
            H = jax.hessian(mean("auto"))(jnp.ones(2))
        second = [
            e["program"] for e in plan.of("derivative") if e["strategy"] == "second derivative"
        ]
        assert "jacobian" in second, plan
        assert bool(plan.of("settle")) == ("settle" in passes), plan
        assert _rel(H, ref) < 1e-12


def test_reverse_over_reverse_transposes_by_columns():
    """``jacrev`` of ``jacrev`` transposes the second derivative's ``linear_call``
    (`_engine.tangents._linear_tangent`). Through at most 8 scalars its transpose runs the
    fast program once per unit tangent (`_transpose_by_columns`: scalarized over a batch
    of 40 here). Through more (10 scalars: a gradient through 2 of them, differentiated
    through all) the run's derivative is the discrete adjoint, whose own derivative is
    JAX's, and nothing is transposed by columns. The plan says which; both equal
    autodiff."""
    ps = jnp.linspace(0.8, 1.2, 40)[:, None]

    def mean(program, P):
        return jnp.mean(jax.vmap(lambda s: _toy_second(P * s, program, True))(ps))

    def transposes(fn, x):
        return [(e["by"], e["scalars"]) for e in s.explain(fn, x).of("transpose")]

    p2 = jnp.array([1.3, 0.7])
    ref = jax.jacrev(jax.jacrev(lambda P: mean("autodiff", P)))(p2)
    hessian = jax.jacrev(jax.jacrev(lambda P: mean("auto", P)))
    assert set(transposes(hessian, p2)) == {("columns", 2)}
    assert _rel(hessian(p2), ref) < 1e-12

    def grad_of_two(program):
        return lambda P: jax.grad(lambda a: mean(program, jnp.concatenate([a, P[2:]])))(P[:2])

    p10 = jnp.linspace(1.3, 0.7, 10)
    ref = jax.jacrev(grad_of_two("autodiff"))(p10)
    plan = s.explain(jax.jacrev(grad_of_two("auto")), p10)
    strategies = {e["strategy"] for e in plan.of("derivative")}
    assert {"checkpointed jvp, discrete adjoint", "second derivative"} <= strategies, plan
    assert not [e for e in plan.of("transpose") if e["by"] == "columns"], plan
    got = jax.jacrev(grad_of_two("auto"))(p10)
    assert np.abs(ref[:, 2:]).max() > 0 and _rel(got, ref) < 1e-12


def test_linear_call_under_a_vmap_it_does_not_depend_on():
    """JAX calls the batching rule of so3jax's ``linear_call`` (`so3jax._engine.linear_call`)
    under every ``vmap`` in scope, also one no argument of the call is batched over; the
    rule must then leave the outputs unbatched (batched, ``out_axes=None`` raises)."""
    p = jnp.linspace(1.3, 0.7, 2)
    g = jax.grad(lambda q: _toy_second(q, "adjoint", False))
    ref = g(p)
    assert np.abs(ref).min() > 0
    got = jax.vmap(lambda _: g(p), out_axes=None)(jnp.arange(3))
    assert _rel(got, ref) < 1e-14


def test_adjoint_program_second_derivatives():
    """``program="adjoint"``'s ``linear_call`` differentiates its residuals through JAX's
    ``jvp`` of the checkpointed program: ``jax.hessian`` equals autodiff's."""
    f = lambda q: _toy_second(q, "adjoint", False)  # noqa: E731
    ref = lambda q: _toy_second(q, "autodiff", False)  # noqa: E731
    p = jnp.array([1.3, 0.7])
    assert _rel(jax.grad(f)(p), jax.grad(ref)(p)) < 1e-12
    H = jax.hessian(ref)(p)
    assert np.abs(H).min() > 0 and _rel(jax.hessian(f)(p), H) < 1e-10


def test_batched_programs_are_traced_once():
    """Under ``vmap`` the array programs are traced once per call: the ``custom_vmap`` and
    its batching rule share one jaxpr (`_engine.layout._dual`), rather than the rule tracing it
    again under its ``vmap``: batching the first trace's jaxpr is cheaper. The plan's
    ``"traced"`` entries count the traces."""
    ps = jnp.array([1.7, -0.4, 2.5])  # fewer runs than the scalarized program takes

    def mean_of_jitted_runs(ps):
        # A jitted run, as `simulate` and `expected_cost` are: its forward program is
        # traced (batched) before ``grad`` linearizes it.
        one = jax.jit(lambda p: _toy(p, "auto"))
        return jnp.mean(jax.vmap(one)(ps))

    plan = s.explain(jax.grad(mean_of_jitted_runs), ps)
    traced = [e["program"] for e in plan.of("traced")]
    assert sorted(traced) == ["jacobian", "run"], plan
    batched = {(e["program"], e["layout"]) for e in plan.of("layout") if e["runs"] == 3}
    assert batched == {("run", "array"), ("jacobian", "array")}, plan
    grads = jax.jit(jax.grad(mean_of_jitted_runs))(ps)
    loop = np.stack([jax.grad(_toy)(p, "autodiff") for p in ps]) / 3
    assert _rel(grads, loop) < 1e-12


def _chain(a0):
    """A loop whose carry becomes batched step by step: ``e`` one step after ``a``, ``b``
    two; ``d`` and the counter never."""

    def step(P, c):
        a, e, b, d, k = c
        return (0.5 * a + P, e + jnp.sin(a), b + e**2, 2.0 * d - 1.0, k + 1)

    observe = lambda P, c: c[2] + c[3]  # noqa: E731
    c0 = (a0, jnp.zeros(()), jnp.zeros(()), jnp.asarray(0.25), jnp.asarray(0, jnp.int32))
    return _engine.run(step, observe, jnp.asarray(0.3), c0, 6, 2)


def _first_scan(jaxpr):
    """The first `scan` equation of ``jaxpr``, searched depth first through sub-jaxprs."""
    from jax.extend.core import subjaxprs

    for e in jaxpr.eqns:
        if e.primitive.name == "scan":
            return e
    for sub in subjaxprs(jaxpr):
        found = _first_scan(sub)
        if found is not None:
            return found
    return None


def test_batched_array_loops_start_settled():
    """Below the scalarized program's batch size, ``vmap`` runs the array program with its
    loops' carries settled up front (the ``"settle"`` pass, in `_engine.layout._Traced`):
    ``e`` and ``b``, which the loop would batch one and two steps in, are batched before
    it, so that JAX batches each loop body once (its own fixed point would batch the outer
    body three times here, and the inner one once per pass); what never depends on the
    batch stays unbatched, and the values are those of single runs. With the pass off,
    JAX's fixed point gives the same loop and values."""
    a0 = jnp.array([0.1, -0.7, 1.3])
    for on in (True, False):
        passes = _engine.policy.PASSES - (set() if on else {"settle"})
        with _engine.policy.using(passes=passes):
            plan = s.explain(jax.vmap(_chain), a0)
            jaxpr = jax.make_jaxpr(jax.vmap(_chain))(a0)
            got = jax.jit(jax.vmap(_chain))(a0)
        expected = [{"kind": "settle", "what": "batched carry", "components": 2}]
        assert plan.of("settle") == (expected if on else []), plan
        scan = _first_scan(jaxpr.jaxpr)  # the save loop (inside the engine's custom rules)
        nc, ncar = sc.scan_split(scan)
        shapes = [v.aval.shape for v in scan.invars[nc : nc + ncar]]
        assert shapes == [(3,), (3,), (3,), (), ()], shapes  # d and the counter shared
        for i, a in enumerate(a0):
            one = _chain(a)
            for g, r in zip(jax.tree.leaves(got), jax.tree.leaves(one), strict=True):
                np.testing.assert_allclose(np.asarray(g)[i], r, rtol=1e-14)


def test_scan_split_reads_loop_operands_and_unknown_loops_fall_back(monkeypatch):
    """`sc.scan_split` finds a loop's constants and carry (JAX 0.10 names the counts;
    0.11 groups the operands instead, checked on a GPU machine's JAX 0.11.2).
    Where it cannot read a loop (``None``, what a later JAX might give), ``vmap`` leaves
    that loop's batching to JAX: nothing settled, the same values."""

    w = jnp.arange(3.0)

    def body(c, x):
        return (c[0] + x * w, c[1] * 2.0), c[1] * x

    closed = jax.make_jaxpr(lambda a, xs: jax.lax.scan(body, (a * w, a), xs))(1.0, jnp.ones(4))
    (scan,) = [e for e in closed.jaxpr.eqns if e.primitive.name == "scan"]
    nc, ncar = sc.scan_split(scan)
    assert ncar == 2 and len(scan.invars) - nc - ncar == 1  # two carried, xs scanned
    assert [v.aval.shape for v in scan.invars[nc : nc + ncar]] == [(3,), ()]
    # JAX 0.11's reading: no counts, the operands in three groups (`ft_in`, whose
    # `unpack` gives them), as the same loop is written there.
    params = {k: v for k, v in scan.params.items() if k not in ("num_consts", "num_carry")}

    class FlatTreeLike:
        def __init__(self, *sizes):
            self.groups = tuple(range(n) for n in sizes)

        def unpack(self):
            return self.groups

    n_xs = len(scan.invars) - nc - ncar
    for ft_in, want in (
        (FlatTreeLike(nc, ncar, n_xs), (nc, ncar)),
        (FlatTreeLike(nc + 1, ncar - 1, n_xs), None),  # groups that do not fit the body
        (None, None),  # no reading at all
    ):
        as_011 = scan.replace(params={**params, "ft_in": ft_in})
        assert sc.scan_split(as_011) == want

    monkeypatch.setattr(sc, "scan_split", lambda e: None)
    a0 = jnp.array([0.1, -0.7, 1.3])
    plan = s.explain(jax.vmap(_chain), a0)
    assert not plan.of("settle"), plan  # the loop is left to JAX's own fixed point
    got = jax.vmap(_chain)(a0)
    for i, a in enumerate(a0):
        for g, r in zip(jax.tree.leaves(got), jax.tree.leaves(_chain(a)), strict=True):
            np.testing.assert_allclose(np.asarray(g)[i], r, rtol=1e-14)


def test_checkpointing_keeps_gradients_and_chunks():
    """Any checkpoint length gives the same gradient. With 23 saved points (a prime) a
    segment of about ``K`` steps holds no divisor of them: the last segment is padded with
    blocks that leave the carry alone, and the discrete adjoint runs them backward too."""
    ref = jax.grad(_toy)(1.7, "autodiff", 21)
    for program in ("auto", "adjoint", "autodiff"):
        for K in (1, 4, 5, 21):
            assert _rel(jax.grad(_toy)(1.7, program, K), ref) < 1e-12
    for n, every, K, segments in ((23, 1, 5, 5), (46, 2, 12, 4)):
        ref = jax.grad(_toy)(1.7, "autodiff", n, n, every)
        toy = functools.partial(_toy, program="adjoint", K=K, n=n, every=every)
        assert _rel(jax.grad(toy)(1.7), ref) < 1e-12
        (entry,) = s.explain(jax.grad(toy), 1.7).of("adjoint")
        assert entry["segments"] == segments and segments * entry["steps_per_segment"] > n
    step = lambda P, c: (c[0] * P, c[1] + 1)
    c0 = (jnp.ones(2), jnp.array(0, jnp.int32))
    ys, cN = _engine.run(step, lambda P, c: c[0][0], 1.5, c0, 21, 3)
    assert ys.shape == (7,) and int(cN[1]) == 21
    np.testing.assert_allclose(ys, 1.5 ** (3 * np.arange(1, 8)))


def test_freeze_on_failure_under_every_transform():
    """A run that blows up freezes and flags itself; its neighbours keep their gradients."""
    sc0 = _seed()

    def cost(k, program):
        sc = with_gains(sc0, k[0], k[1])
        tr = _simulate(sc, SEED_METHOD, jnp.asarray(0.05), jnp.asarray(0.0), 100, 1, program)
        return jnp.nansum(tr.Omega**2), tr.status.code

    ks = jnp.array([[3.0, 1.5], [3.0, 1e5]])  # the second is far past the stable step
    ref = _jit_grad(lambda k: cost(k, "autodiff")[0])(ks[0])
    vg = jax.value_and_grad(lambda k: cost(k, "auto"), has_aux=True)
    (c, code), g = jax.vmap(vg)(ks)
    assert int(code[0]) == 0 and int(code[1]) != 0
    assert np.isfinite(np.asarray(c[0]))
    assert _rel(g[0], ref) < 1e-10 and np.all(np.isfinite(np.asarray(g[0])))


def test_bad_program_is_rejected():
    with pytest.raises(ValueError, match="program"):
        _engine.run(lambda P, c: c, lambda P, c: c, 1.0, jnp.zeros(2), 4, program="fast")
    with pytest.raises(TypeError, match="method"):
        s.simulate(s.scenes.seed(), "RKMK4", 0.01, 10)
    with pytest.raises(ValueError, match="n_steps"):
        s.simulate(s.scenes.seed(), s.RKMK4(), 0.01, 10, save_every=3)


def _seed_mean_cost(key, B: int, n_steps: int, save_every: int = 1):
    """``cost(program)``: the mean seed cost over ``B`` random starts as a function of the
    two gains, run by the engine's ``program``. With ``save_every`` 1 the cost's integral
    is summed in the loop's carry; otherwise the integrand is saved every ``save_every``
    steps (`so3jax._tune._rollout`)."""
    sc0 = _seed()
    R0, W0 = s.initial_states(key, B)

    def cost(program):
        return lambda k: s.expected_cost(
            sc0,
            k[0],
            k[1],
            R0,
            W0,
            SEED_METHOD,
            DT,
            n_steps,
            program=program,
            save_every=save_every,
        )

    return cost


def test_scalarized_jacobian_program_for_large_batches():
    """32 starts or more: the Jacobian program runs scalarized (fusion cuts included).
    With two gains the default reverse mode takes the Jacobian's columns from it, and
    equals JAX's autodiff; so does ``jacfwd``. The columns are the outer axis of every
    tangent component, ``(2, B)`` arrays, not ``(B, 2)``
    (`_engine.passes.scalarized.columns_outside`)."""
    B = _engine.policy.batched_layout("jacobian")[1]
    for save_every in (1, 2):  # the integral summed in the carry; saved points
        cost = _seed_mean_cost(jax.random.PRNGKey(3), B, N, save_every)
        f = _jit_grad(cost("auto"))
        assert "conditional(" in f.lower(K0).compile().as_text()  # scalarized, with cuts
        ref = _jit_grad(cost("autodiff"))(K0)
        assert _rel(f(K0), ref) < 1e-10
        jf = jax.jit(jax.jacfwd(cost("auto")))
        assert _rel(jf(K0), ref) < 1e-10
    # With saved points nothing but the columns-outside layout appears (summed in the
    # carry, the final state's tangents are moved once, after the loop, for the output).
    hlo = jf.lower(K0).as_text()
    assert f"tensor<2x{B}xf64>" in hlo and f"tensor<{B}x2xf64>" not in hlo
    # the Hessian's jvp of that program too (its values: test_second_derivatives_...),
    # where it runs scalarized (from batched_layout["jvp"]'s runs; here made B's)
    layouts = dict(_engine.policy.current().batched_layout)
    with _engine.policy.using(batched_layout={**layouts, "jvp": (B, B)}):
        hlo = jax.jit(jax.hessian(cost("auto"))).lower(K0).as_text()
    assert f"tensor<{B}x2xf64>" not in hlo


def test_scalarized_jacobian_cuts_what_its_columns_consume(engine_policy):
    """From ``column_cuts_from`` runs the scalarized Jacobian program also cuts the values
    its tangent columns consume (the policy's ``column_cut_cone``): more cuts in the
    program, and ``grad`` still equals JAX's autodiff (here from 16 runs, at 16)."""
    B = _engine.policy.batched_layout("jacobian")[1]
    cost = _seed_mean_cost(jax.random.PRNGKey(5), B, N)

    def cuts():
        jax.clear_caches()  # JAX keeps the traced derivative of the run's jitted program
        return _jit_grad(cost("auto")).lower(K0).as_text().count("stablehlo.case")

    with _engine.policy.using(column_cuts_from=B + 1):
        plain = cuts()
    engine_policy(column_cuts_from=B)
    assert cuts() > plain > 0
    ref = _jit_grad(cost("autodiff"))(K0)
    assert _rel(_jit_grad(cost("auto"))(K0), ref) < 1e-10
    jax.clear_caches()  # leave no program with these cuts to later tests


def test_scalarized_jacobian_without_cuts(engine_policy):
    """The scalarized Jacobian program without fusion cuts (a GPU's, from 4096 runs there),
    with its columns outside the runs: ``grad`` and ``jacfwd`` equal JAX's autodiff,
    here at 32 runs on the CPU."""
    B = 32
    layouts = dict(_engine.policy.current().batched_layout)
    engine_policy(batched_layout={**layouts, "jacobian": (B, None)})
    cost = _seed_mean_cost(jax.random.PRNGKey(4), B, N - 1)
    jf = jax.jit(jax.jacfwd(cost("auto")))
    hlo = jf.lower(K0).as_text()
    assert f"tensor<2x{B}xf64>" in hlo and "conditional" not in jf.lower(K0).compile().as_text()
    ref = _jit_grad(cost("autodiff"))(K0)
    assert _rel(jf(K0), ref) < 1e-10
    assert _rel(_jit_grad(cost("auto"))(K0), ref) < 1e-10


def test_batch_tiles_policy(monkeypatch):
    """`_engine.batch_tiles`: the Jacobian program over a CPU batch runs in tiles of about
    ``192 / (1 + columns)`` runs (multiples of 8) that cover the batch: 64 for two gains
    (from 96 runs), 32 for six; other programs, smaller batches, runs that observe more
    than a few scalars per saved point and other backends run whole."""
    assert _engine.passes.tiles.batch_tiles("jacobian", 256, 2) == (4, 64)
    assert _engine.passes.tiles.batch_tiles("jacobian", 256, 6) == (8, 32)
    assert _engine.passes.tiles.batch_tiles("jacobian", 100, 2) == (2, 56)
    assert _engine.passes.tiles.batch_tiles("jacobian", 95, 2) == (1, 95)
    assert _engine.passes.tiles.batch_tiles("run", 4096) == (1, 4096)
    assert _engine.passes.tiles.batch_tiles("jacobian", 256, 2, observed=40) == (
        1,
        256,
    )  # trajectories
    for B in range(96, 1100, 7):
        n, size = _engine.passes.tiles.batch_tiles("jacobian", B, 2)
        assert size % 8 == 0 and n * size >= B > (n - 1) * size and 40 <= size <= 96
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert _engine.passes.tiles.batch_tiles("jacobian", 256, 2) == (1, 256)


def test_scalarized_jacobian_of_trajectories():
    """The scalarized one-pass Jacobian (32 runs) of a cost on whole trajectories: each
    saved point has many components (``R``, ``Omega``, ``Rd``, ``M``, ``e_R``,
    ``e_Omega``), values and columns. ``jacfwd`` and ``grad`` equal JAX's autodiff, and
    the value equals the forward run."""
    B = _engine.policy.batched_layout("jacobian")[1]
    sc0 = _seed()
    R0, W0 = s.initial_states(jax.random.PRNGKey(6), B)

    def cost(program):
        def f(k):
            sc = with_gains(sc0, k[0], k[1])

            def one(R, W):
                sc1, R1 = with_start(sc, R, W)
                tr = _simulate(
                    sc1, SEED_METHOD, jnp.asarray(DT), jnp.asarray(0.0), N - 2, 1, program, R0=R1
                )
                ex = tr.extras
                return (
                    jnp.sum(tr.Omega**2)
                    + jnp.sum(jnp.sin(tr.M))
                    + jnp.sum(tr.R * tr.Rd)
                    + jnp.sum(ex["e_R"] * ex["e_Omega"])
                )

            return jnp.mean(jax.vmap(one)(R0, W0))

        return f

    ref = _jit_grad(cost("autodiff"))(K0)
    jf = jax.jit(jax.jacfwd(cost("auto")))
    assert "conditional(" in jf.lower(K0).compile().as_text()  # scalarized, with cuts
    assert _rel(jf(K0), ref) < 1e-10
    assert _rel(_jit_grad(cost("auto"))(K0), ref) < 1e-10
    value, _ = jax.jit(lambda k: jax.jvp(cost("auto"), (k,), (jnp.ones(2),)))(K0)
    assert _rel(value, jax.jit(cost("array"))(K0)) < 1e-12


def test_jacobian_observation_kinds():
    """The one-pass Jacobian saves each observation as its tangent needs: nothing for one
    that depends on no differentiated input (a reference attitude stacked in the body's
    carry leaf), three numbers for a rotation (a right frame ``R hat(xi)``, a left one for
    ``R^T``), nine for anything else: the plan's ``"observations"`` entry says so. ``grad``
    and ``jacfwd`` of a cost on all of them equal autodiff: one run (array program) and 32
    (scalarized)."""
    from so3jax import _updates

    def step(P, c):
        R, w = c
        k, wd = P
        w1 = w - 0.05 * k * (w - wd) + 0.05 * jnp.cross(w, R[0, 2])
        ref = _updates._rmul_exp(R[1], jnp.array([0.02, 0.0, -0.01]))  # moved by no input
        return jnp.stack([_updates._rmul_exp(R[0], 0.05 * w1), ref]), w1

    def observe(P, c):
        R, w = c
        return {"R": R[0], "RT": R[0].T, "ref": R[1], "prod": R[0] @ R[1], "w": w}

    def cost(program, R0):
        def f(P):
            ys, cN = _engine.run(
                step, observe, P, (R0, jnp.array([0.3, -0.2, 0.5])), 12, 2, program=program
            )
            return sum(jnp.sum(jnp.sin(y * (i + 1))) for i, y in enumerate(jax.tree.leaves(ys)))

        return f

    saved = set()
    P = (jnp.asarray(2.0), jnp.array([0.4, 0.1, -0.3]))
    Rs = s.exp(jax.random.normal(jax.random.PRNGKey(3), (32, 3)))
    for B in (1, 32):
        R0 = jnp.stack([Rs[:B], jnp.broadcast_to(Rs[-1], (B, 3, 3))], axis=1)

        def mean(program, R0=R0):
            return lambda P: jnp.mean(jax.vmap(lambda R: cost(program, R)(P))(R0))

        if B == 1:
            mean = lambda program, R0=R0: cost(program, R0[0])  # noqa: E731
        ref = jax.jit(jax.grad(mean("autodiff")))(P)
        for d in (jax.grad, jax.jacfwd):
            saved |= {e["saved"] for e in s.explain(d(mean("auto")), P).of("observations")}
            got = jax.jit(d(mean("auto")))(P)
            for g, r in zip(jax.tree.leaves(got), jax.tree.leaves(ref), strict=True):
                assert _rel(g, r) < 1e-10, (B, d.__name__)
    # leaves in key order: R, RT, prod, ref, w
    assert saved == {("right frame", "left frame", "dense", "none", "dense")}


def test_frame_dense_and_its_transpose():
    """`_engine.passes.frames._frame_dense` is `so3jax._engine.passes.frames.dense` (right and
    left frames), and JAX's
    transposes of the two agree."""
    from so3jax._engine.passes.frames import Frame, dense

    R = jax.random.normal(jax.random.PRNGKey(1), (4, 3, 3))
    xi = jax.random.normal(jax.random.PRNGKey(2), (4, 3))
    ct = jax.random.normal(jax.random.PRNGKey(3), (4, 3, 3))
    for left in (False, True):
        want = dense(R, Frame(xi, left))
        assert _rel(_engine.passes.frames._frame_dense(R, xi, left), want) < 1e-15
        t_got = jax.linear_transpose(lambda x: _engine.passes.frames._frame_dense(R, x, left), xi)(
            ct
        )[0]
        t_want = jax.linear_transpose(lambda x: dense(R, Frame(x, left)), xi)(ct)[0]
        assert _rel(t_got, t_want) < 1e-14


def test_one_pass_jacobian_through_gains_and_initial_rates():
    """A few inputs (2 gains + 3 initial rates): value and derivatives from one pass.

    The value equals the plain forward run, ``grad`` equals JAX's autodiff of the
    array program (``jacfwd`` and ``vmap(grad)`` through the same program:
    `test_vmap_of_grad_equals_loop_of_grads`, `test_freeze_on_failure_under_every_transform`),
    and the tangent program leaves the reference attitude out (it does not depend on the
    gains: the plan's ``carried``).
    """
    sc0 = _seed()
    R0 = s.random_rotation(jax.random.PRNGKey(5), (1,))

    def cost(x, R, program="auto"):
        sc, R1 = with_start(with_gains(sc0, x[0], x[1]), R, x[2:])
        tr = _simulate(sc, SEED_METHOD, jnp.asarray(DT), jnp.asarray(0.0), N + 1, 1, program, R0=R1)
        return jnp.sum(tr.Omega**2) + jnp.sum(tr.M[-1] ** 2) + jnp.sum(tr.R[-1] * tr.Rd[-1])

    x = jnp.array([3.0, 1.5, 0.1, -0.2, 0.3])
    (chosen,) = s.explain(jax.grad(cost), x, R0[0]).of("derivative")
    # carry float leaves: body attitude, reference attitude, rates and memory
    # (the rates reach the engine twice: in the scene and in the carry)
    assert chosen["strategy"] == "one-pass Jacobian" and chosen["scalars"] == 8
    assert chosen["carried"] == (True, False, True)
    v, g = jax.value_and_grad(cost)(x, R0[0])
    np.testing.assert_allclose(v, cost(x, R0[0]), rtol=1e-14)
    assert _rel(g, jax.jit(jax.grad(cost), static_argnums=2)(x, R0[0], "autodiff")) < 1e-10


def test_dependence_walk():
    """`_engine.masks._depends` keeps stacked parts apart, ignores flags, takes loops whole."""

    def f(a, b, c):
        s = jnp.stack([a, b]) * 2.0
        ok = jnp.all(jnp.isfinite(s))
        frozen = jnp.where(ok, s[1], b)  # b's part only: the predicate carries no tangent
        looped = jax.lax.scan(lambda x, _: (x * c, None), a, None, length=3)[0]
        return s[0], frozen, looped, ok.astype(a.dtype)

    x = jnp.ones(3)
    assert _engine.masks._depends(f, [x, x, x], [True, False, False]) == [True, False, True, False]
    assert _engine.masks._depends(f, [x, x, x], [False, True, False]) == [False, True, False, False]
    assert _engine.masks._depends(f, [x, x, x], [False, False, True]) == [False, False, True, False]

    def g(a, b):  # a fusion cut keeps the parts apart: its integer index carries no tangent
        s = jnp.stack([a, b])
        (t,) = cuts.array_cut(cuts.array_cut_index(s), s)
        return t[0], t[1]

    assert _engine.masks._depends(g, [x, x], [True, False]) == [True, False]
    assert _engine.masks._depends(g, [x, x], [False, True]) == [False, True]

    def h(a, b):  # every reduction the scalarizer knows keeps the reduced rows apart
        s = jnp.stack([a, b])
        return jnp.prod(s, axis=1)[0], jnp.sum(s, axis=1)[1], jnp.max(s, axis=1)[0]

    assert _engine.masks._depends(h, [x, x], [True, False]) == [True, False, True]
    assert _engine.masks._depends(h, [x, x], [False, True]) == [False, True, False]


def test_gpu_layout_table(monkeypatch):
    """On a GPU `batched_layout` takes ``gpu_layout``'s entries, and the plan says so
    (`so3jax.explain`): a batch of 64 runs (scalarized on the CPU) runs the array program
    there, as many runs as its ``"run"`` entry the scalarized one; the one-pass Jacobian
    of ``jacfwd`` over 64 runs is the array program there too; the other programs keep
    the CPU's table. (That both layouts give the same numbers is `test_scalarize.py`'s.)
    Traces only: compiling them would cost the suite seconds."""
    sc = s.scenes.seed()
    R0s = s.random_rotation(jax.random.key(4), (64,))
    big = jax.ShapeDtypeStruct((dict(_engine.policy.DEFAULT.gpu_layout)["run"][0], 3, 3), R0s.dtype)

    def batch(R0s):
        return jax.vmap(lambda R0: s.simulate(sc, s.RKMK4(), DT, 4, 2, R0=R0).R)(R0s)

    def jacobian(R0s):
        def cost(k):
            sc_k = with_gains(sc, k[0], k[1])
            return jax.vmap(lambda R0: s.simulate(sc_k, s.RKMK4(), DT, 4, 2, R0=R0).R)(R0s)

        return jax.jacfwd(cost)(jnp.array([8.81, 2.54]))

    def layouts(fn, R0s, program):
        plan = s.explain(fn, R0s)
        return [(e["runs"], e["layout"]) for e in plan.of("layout") if e["program"] == program]

    table = dict(_engine.policy.DEFAULT.batched_layout)
    assert _engine.policy.batched_layout("run") == table["run"]
    assert table["run"][0] <= 64 and table["jacobian"][0] <= 64  # scalarized on the CPU
    assert layouts(batch, R0s, "run") == [(64, "scalarized")]
    assert layouts(jacobian, R0s, "jacobian") == [(64, "scalarized")]
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    try:
        gpu = dict(_engine.policy.DEFAULT.gpu_layout)
        for program in ("run", "jacobian", "jvp"):
            assert _engine.policy.batched_layout(program) == gpu[program]
        assert _engine.policy.batched_layout("adjoint") == (None, None)  # array only
        assert layouts(batch, R0s, "run") == [(64, "array")]
        assert layouts(batch, big, "run") == [(big.shape[0], "scalarized")]
        # jacfwd in (k_R, k_Omega) of 64 runs: the Jacobian program, array layout
        assert layouts(jacobian, R0s, "jacobian") == [(64, "array")]
    finally:
        monkeypatch.undo()
    assert _engine.policy.batched_layout("run") == table["run"]


def test_sweep_program_default_per_platform(monkeypatch):
    """`sweep` leaves its program to the engine unless told: scalarized on a CPU, the
    array program on a GPU (`_engine.policy.Policy.sweep_scalarize`, read by
    `_sweep.sweep_scalarize`); a forced choice is kept. `SweepResult.scalarize` says
    which ran; the results agree to round-off."""
    from so3jax import _sweep

    class FakeGPU:
        platform = "gpu"

    assert _sweep.sweep_scalarize(jax.devices("cpu")) is True
    assert _sweep.sweep_scalarize([FakeGPU()]) is False
    kw = dict(n_attitudes=3, dt=1e-3, n_steps=20, method=s.LieEuler(), progress=False)
    # (the platform's choice, the caller's): False as on a GPU, True as on a CPU
    ran = []
    for choice, forced in ((False, None), (True, None), (False, True)):
        monkeypatch.setattr(_sweep, "sweep_scalarize", lambda devices, c=choice: c)
        ran.append(s.sweep(s.scenes.seed(), [2.0], [1.0], scalarize=forced, **kw))
    assert [r.scalarize for r in ran] == [False, True, True]
    assert _rel(ran[1].final_psi, ran[0].final_psi) < 1e-12


def test_sweep_chunk_default_per_platform():
    """`sweep`'s default chunk: 1024 runs per CPU device; on a GPU 65536 per device, cut
    to half the smallest device's memory, never below 1024."""
    from so3jax import _sweep

    class FakeGPU:
        platform = "gpu"

        def __init__(self, limit):
            self.limit = limit

        def memory_stats(self):
            if self.limit == "raise":
                raise RuntimeError("no statistics")
            return None if self.limit is None else {"bytes_limit": self.limit}

    cpu = jax.devices("cpu")[0]
    assert _sweep.sweep_chunk([cpu], 1001, 8) == 1024
    assert _sweep.sweep_chunk([cpu] * 3, 10**6, 8) == 3 * 1024
    big = 141 * 2**30
    assert _sweep.sweep_chunk([FakeGPU(big)], 1001, 8) == 65536
    assert _sweep.sweep_chunk([FakeGPU(big)] * 2, 1001, 4) == 2 * 65536
    # 40 GiB, 1001 points of 48 float64 numbers: half holds 55,868 runs.
    per = (40 * 2**30 // 2) // (1001 * 48 * 8)
    assert 1024 < per < 65536
    assert _sweep.sweep_chunk([FakeGPU(40 * 2**30)], 1001, 8) == per
    # The smallest device decides; unknown memory counts as 16 GiB; never below 1024.
    small = [FakeGPU(big), FakeGPU(40 * 2**30)]
    assert _sweep.sweep_chunk(small, 1001, 8) == 2 * per
    assert _sweep.sweep_chunk([FakeGPU(None)], 1001, 8) == (8 * 2**30) // (1001 * 384)
    assert _sweep.sweep_chunk([FakeGPU("raise")], 10**6, 8) == 1024


def test_array_programs_cut_where_xla_would_recompute(monkeypatch, count_cuts):
    """On the CPU the array programs' derivative rules and Runge-Kutta stages go through
    fusion cuts (`cuts.array_cut_index`): the Jacobian program over a small batch has them,
    a single RKMK4 run's forward pass none (its stages cut only when differentiated),
    RKMK45's forward pass one per stage read three times or more; a GPU none."""
    sc0 = s.scenes.seed()
    R0s = s.random_rotation(jax.random.key(5), (4,))

    def batch_cost(k):
        return jnp.mean(jax.vmap(lambda R0: _one_cost(sc0, k, R0, s.RKMK4()))(R0s))

    k = jnp.array([8.81, 2.54])
    jac = count_cuts(jax.make_jaxpr(jax.jacfwd(batch_cost))(k).jaxpr)
    fwd = count_cuts(jax.make_jaxpr(lambda k: _one_cost(sc0, k, R0s[0], s.RKMK4()))(k).jaxpr)
    rk45 = count_cuts(jax.make_jaxpr(lambda k: _one_cost(sc0, k, R0s[0], s.RKMK45()))(k).jaxpr)
    assert jac == 4 * 2 + 4  # 4 exponential updates (matrices, tangent) and 4 stages
    assert fwd == 0
    assert rk45 == 5  # DOPRI5's stages 1 to 5 (read 7, 4, 5, 4, 3 times)
    jax.clear_caches()  # the traces above hold the CPU's cuts
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    try:
        assert count_cuts(jax.make_jaxpr(jax.jacfwd(batch_cost))(k).jaxpr) == 0
    finally:
        monkeypatch.undo()
        jax.clear_caches()


def _one_cost(scene, k, R0, method):
    sc_k, R = with_start(with_gains(scene, k[0], k[1]), R0, jnp.zeros(3))
    return jnp.sum(s.simulate(sc_k, method, DT, 4, 2, R0=R).Omega ** 2)


def _compiled_text(f, *args) -> str:
    return jax.jit(f).lower(*args).compile().as_text()


def _hoisted_in(text: str) -> bool:
    """Whether a compiled program holds a loop `_engine.passes.hoist._hoisted` made one kernel. XLA
    tags small loops of its own with ``xla_cpu_small_call`` too (JAX 0.12's XLA also
    some that `_hoisted` left alone), but only `_hoisted` keeps its call from inlining."""
    return 'inlineable="false"' in text


#: Tests that force hoisting on: only on the jaxlib releases the suite has passed on
#: with it (`_engine._jax.HOIST_TESTED`); elsewhere the engine leaves it off.
needs_hoisting = pytest.mark.skipif(
    not _engine.policy.hoisting_verified(),
    reason="hoisting is off on this jaxlib (_jax.HOIST_TESTED)",
)


@needs_hoisting
@pytest.mark.parametrize("runs", [1])  # (a batch: tests/passes/test_pass_hoist.py)
def test_hoisted_loops_equal_the_default_runtime(runs, engine_policy):
    """Loops compiled as one kernel (`_engine.passes.hoist._hoisted`) give XLA's default runtime's
    numbers: a single run (array program) and 40 runs (scalarized), forward pass,
    ``grad`` and ``jacfwd`` (the one-pass Jacobian program), in one process."""
    R0, W0 = s.initial_states(jax.random.key(3), runs)
    sc0 = _seed()

    def cost(k):
        sc = with_gains(sc0, k[0], k[1])

        def one(R, W):
            scR, R = with_start(sc, R, W)
            dt, t0 = jnp.asarray(DT), jnp.asarray(0.0)
            tr = _simulate(scR, s.RKMK4(), dt, t0, N, 1, "auto", R0=R)
            return jnp.sum(tr.Omega**2) + jnp.sum(tr.R[-1] * tr.Rd[-1])

        return jnp.mean(jax.vmap(one)(R0, W0)) if runs > 1 else one(R0[0], W0[0])

    k = jnp.array([8.81, 2.54])
    out = {}
    for hoist in (True, False):
        passes = _engine.policy.PASSES - ({"hoist"} if not hoist else set())
        engine_policy(passes=passes)
        jax.clear_caches()  # the choice is made when a program is traced
        out[hoist] = {}
        fns = {"value": cost, "grad": jax.grad(cost)}
        if runs == 1:  # (40 runs: the same Jacobian program as ``grad``)
            fns["jacfwd"] = jax.jacfwd(cost)
        for name, f in fns.items():
            compiled = jax.jit(f).lower(k).compile()
            # (the array layout's derivative programs with their reductions written out)
            assert _hoisted_in(compiled.as_text()) == hoist
            out[hoist][name] = np.asarray(compiled(k))
    for name in out[True]:
        np.testing.assert_allclose(out[True][name], out[False][name], rtol=1e-12, atol=0)
    jax.clear_caches()


def test_hoisted_call_returns_its_inputs(engine_policy):
    """The call `_hoisted` makes returns its inputs after the loop's outputs, so they stay
    live to its end: on JAX 0.11 and 0.12 XLA otherwise gave an input's memory to a value
    inside the loop, and its older emitter aborted the process (CI's JAX 0.10 never
    did, so this checks the program's form). Traces only."""
    engine_policy(passes=_engine.policy.PASSES)
    step = lambda P, c: jnp.tanh(P[0] * c + P[1])
    f = lambda b: _engine.run(step, lambda P, c: c, (0.5, b), jnp.ones(3), 5)[0]

    jaxpr = jax.make_jaxpr(jax.vmap(f))(jnp.zeros((20, 3))).jaxpr
    (call,) = [e for e, _ in sc.equations(jaxpr) if e.params.get("name") == "call"]
    inner = call.params["jaxpr"].jaxpr
    n = len(inner.invars)
    assert len(inner.outvars) > n and list(inner.outvars[-n:]) == list(inner.invars)


@needs_hoisting
def test_hoisting_keeps_out_what_one_kernel_cannot_hold(monkeypatch):
    """No hoisting for a loop with a dot (XLA's older emitter refuses it), nor with a
    reduction over more than 1024 elements, nor for one whose batch exceeds
    ``hoist_max_bytes``; closed-over constants larger than the older
    emitter takes (12 kB here) reach a hoisted loop as arguments, with the same numbers."""

    def step(P, c):
        A, b = P
        return jnp.tanh(A @ c + b)

    def loop(step, P, c0):
        return _engine.run(step, lambda P, c: c, P, c0, 5)[0]

    # 20 runs: the array program, vmapped (its dot stays a dot), over the 1 kB under
    # which XLA hoists a loop itself (``xla_cpu_small_while_loop_byte_threshold``).
    layouts = dict(_engine.policy.current().batched_layout)
    array_only = _engine.policy.using(batched_layout={**layouts, "run": (None, None)})
    array_only.__enter__()  # (array programs, until the policy is restored below)
    A, bs = jnp.eye(3) * 0.5, jnp.zeros((20, 3))
    text = _compiled_text(jax.vmap(lambda b: loop(step, (A, b), jnp.ones(3))), bs)
    assert not _hoisted_in(text)
    elementwise = lambda P, c: jnp.tanh(P[0] * c + P[1])
    text = _compiled_text(jax.vmap(lambda b: loop(elementwise, (0.5, b), jnp.ones(3))), bs)
    assert _hoisted_in(text)

    # A reduction over more than hoist_max_reduced elements of the batch: XLA would make
    # it a kernel the older emitter lacks ("Fusion kind not implemented on CPU"). Over at
    # most unroll_max_terms terms a run it is written out and the loop hoisted (a 6x6
    # product as _so3._mm forms it: 216 elements a run, 1080 over 5 runs); over more
    # terms (a sum of 64 here) the loop is not hoisted past 1024 elements (the
    # array layout's batches: the scalarized programs have no reductions).
    def matmul(P, c):
        return jnp.tanh(jnp.sum(P[0][:, :, None] * c[None, :, :], axis=1) + P[1])

    def mean(P, c):
        return jnp.tanh(P[0] * c + jnp.sum(c) / 64 + P[1])

    A6 = jnp.eye(6) * 0.5
    # (step, start, runs, hoisted, reductions left in the program)
    cases = ((matmul, jnp.eye(6), 4, True, True), (matmul, jnp.eye(6), 5, True, False))
    cases += ((mean, jnp.ones(64), 16, True, True), (mean, jnp.ones(64), 17, False, True))
    for step, c0, runs, hoisted, reduces in cases:
        P = A6 if step is matmul else 0.5
        f = jax.vmap(lambda b, step=step, c0=c0, P=P: loop(step, (P, b), c0))
        text = _compiled_text(f, jnp.zeros((runs,) + c0.shape))
        assert _hoisted_in(text) == hoisted
        assert (" reduce(" in text) == reduces
        got = jax.jit(f)(jnp.full((runs,) + c0.shape, 0.1))
        c, want = c0, []
        for _ in range(5):
            c = jnp.tanh((A6 @ c if step is matmul else 0.5 * c + jnp.mean(c)) + 0.1)
            want.append(c)
        np.testing.assert_allclose(got, jnp.broadcast_to(jnp.stack(want), got.shape), rtol=1e-14)

    array_only.__exit__(None, None, None)  # (the engine's own layouts again)
    with _engine.policy.using(hoist_max_bytes=1000):  # 200 float64 runs: over
        batch = jax.vmap(lambda b: loop(elementwise, (0.5, b), jnp.ones(3)))
        assert not _hoisted_in(_compiled_text(batch, jnp.zeros((200, 3))))
        assert _hoisted_in(_compiled_text(batch, jnp.zeros((100, 3))))

    starts = jnp.asarray(np.random.default_rng(0).normal(size=(1500, 3)))  # 12 kB a leaf
    runs = lambda b: jax.vmap(lambda c: loop(elementwise, (0.5, b), c))(starts)
    text = _compiled_text(runs, jnp.float64(0.1))
    assert _hoisted_in(text)
    got = jax.jit(runs)(jnp.float64(0.1))
    c, want = starts, []
    for _ in range(5):
        c = jnp.tanh(0.5 * c + 0.1)
        want.append(c)
    # (round-off: JAX 0.11's XLA differs from the eager steps in the last bit or two)
    np.testing.assert_allclose(got, jnp.stack(want, 1), rtol=1e-12)


def _reductions(jaxpr) -> list:
    return [e for e, _ in sc.equations(jaxpr) if e.primitive.name.startswith("reduce_")]


def test_small_reductions_written_out_term_by_term():
    """`_engine.passes.unroll._unrolled` (what lets derivative programs' loops be hoisted)
    writes out
    sums, products, maxima, minima, all and any over at most ``unroll_max_terms`` terms, in
    nested loops and branches too, with the same numbers; a larger one stays."""
    rng = np.random.default_rng(0)
    A, B = jnp.asarray(rng.normal(size=(3, 3))), jnp.asarray(rng.normal(size=(3, 3)))
    v, m = jnp.asarray(rng.normal(size=3)), jnp.array([True, False, True])

    def f(A, B, v, m):
        P = jnp.sum(A[:, :, None] * B[None, :, :], axis=1)  # as _so3._mm
        s = jnp.sum(P * P, axis=(0, 1))  # 9 terms
        pr = jnp.prod(v[:, None] * jnp.ones((3, 2)), axis=0)  # (through a broadcast)
        body = lambda c, _: (jnp.sum(c[:, None] * A, axis=0), jnp.max(c))
        c, cs = jax.lax.scan(body, v, None, length=3)
        big = jnp.sum(jnp.arange(40.0) * s)  # 40 terms: left as is
        branch = jax.lax.cond(s > 1, lambda: jnp.sum(v), lambda: jnp.min(jnp.exp(v)))
        return P, s, pr, c, cs, big, branch, jnp.all(m), jnp.any(m), jnp.min(v, axis=0)

    closed = jax.make_jaxpr(f)(A, B, v, m)
    out = _engine.passes.unroll._unrolled(closed)
    assert len(_reductions(closed.jaxpr)) == 11
    assert [e.params["axes"] for e in _reductions(out.jaxpr)] == [(0,)]  # the 40 terms
    got = jax.core.eval_jaxpr(out.jaxpr, out.consts, A, B, v, m)
    for g, w in zip(got, f(A, B, v, m), strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-15, atol=1e-15)
    # The terms are summed in row-major order, as the matrix product sums them; agreement to
    # round-off, not bit for bit: XLA may contract a product and a sum into one fused
    # multiply-add in one program and not in the other (its default flags on JAX 0.12).
    np.testing.assert_allclose(np.asarray(got[0]), np.asarray(A @ B), rtol=1e-15, atol=1e-15)
    # a reduction of a leaf used elsewhere is sliced from it, a literal's reduced as is
    g = lambda x: x * jnp.sum(x)
    assert not _reductions(_engine.passes.unroll._unrolled(jax.make_jaxpr(g)(v)).jaxpr)


def test_hoisting_can_be_turned_off_from_the_environment():
    """``SO3JAX_HOIST_LOOPS=0``: the way out should XLA's older emitter refuse a loop;
    ``1`` asks for hoisting on a jaxlib the suite has not passed on. Unset, loops are
    hoisted only on the jaxlib releases of `_jax.HOIST_TESTED` (a loop XLA cannot compile
    that way aborts the process), and elsewhere held back with a warning
    (`test_jax_gate.py`)."""
    import jaxlib

    code = "from so3jax._engine import policy as p; print(p.DEFAULT.on('hoist'), p.HOIST_HELD_BACK)"
    release = tuple(int(x) for x in jaxlib.__version__.split(".")[:2])
    verified = release in _engine._jax.HOIST_TESTED
    assert verified == _engine.policy.hoisting_verified()
    cases = (("0", "False False"), ("1", "True False"), (None, f"{verified} {not verified}"))
    for value, want in cases:
        env = dict(os.environ, JAX_PLATFORMS="cpu")
        env.pop("SO3JAX_HOIST_LOOPS", None)
        if value is not None:
            env["SO3JAX_HOIST_LOOPS"] = value
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
        assert out.stdout.strip() == want, out.stderr


def test_vmap_of_grad_around_hoisted_loops_compiles():
    """A ``vmap`` around a staged derivative batches its loops after `_hoisted` chose: 40
    gain sets of the gradient of a 16-start mean cost (reductions over 40 x 16 x 27
    elements there) compile and equal the gradients one by one."""
    R0, W0 = s.initial_states(jax.random.key(5), 16)
    sc0 = _seed()

    def cost(kR):
        return s.expected_cost(sc0, kR, 2.5, R0, W0, s.RKMK4(), DT, 10, checkpoint_every=None)

    ks = jnp.linspace(1.0, 9.0, 40)
    got = jax.jit(jax.vmap(jax.grad(cost)))(ks)
    one = jax.jit(jax.grad(cost))
    np.testing.assert_allclose(np.asarray(got)[[0, -1]], [one(ks[0]), one(ks[-1])], rtol=1e-12)
