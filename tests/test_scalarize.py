"""Scalarized stepping: same numbers as the array program, under jit, vmap and grad."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import so3jax
from so3jax._engine.passes.scalarize import (
    ScalarizeError,
    from_components,
    scalarize,
    to_components,
)
from so3jax._tune import with_gains

# One method per engine (RKMK in both coordinates, commutator-free, LGVI); LieEuler
# also runs in the gradient test. Kept short: scalarized programs compile slowly.
METHODS = {
    "RKMK4": so3jax.RKMK4(),
    "RKMK4-cayley": so3jax.RKMK4(coords="cayley"),
    "CF4": so3jax.CF4(),
    "LGVI": so3jax.LGVI(),
}


def _run(scene, method, scalarize, n=60, dt=0.02):
    return so3jax.simulate(scene, method, dt, n, save_every=20, scalarize=scalarize)


@pytest.mark.parametrize("name", list(METHODS))
def test_scalarized_simulate_matches_array_program(name):
    method = METHODS[name]
    scenes = [so3jax.scenes.seed()]
    if name in ("RKMK4", "LGVI"):
        scenes.append(so3jax.scenes.dzhanibekov())
    for scene in scenes:
        a, b = _run(scene, method, False), _run(scene, method, True)
        for x, y in ((a.R, b.R), (a.Omega, b.Omega), (a.t, b.t)):
            np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=0, atol=1e-14)
        assert int(b.status.code) == int(a.status.code) == 0
        if a.M is not None:
            np.testing.assert_allclose(np.asarray(b.M), np.asarray(a.M), rtol=0, atol=1e-13)


def test_scalarized_float32():
    scene = so3jax.scenes.seed(dtype=jnp.float32)
    a, b = _run(scene, so3jax.RKMK4(), False), _run(scene, so3jax.RKMK4(), True)
    assert b.R.dtype == jnp.float32 and b.y.x.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(b.R), np.asarray(a.R), rtol=0, atol=2e-6)


def test_scalarized_vmap_and_grad_match():
    scene = so3jax.scenes.seed()
    R0s = so3jax.random_rotation(jax.random.key(3), (5,))
    gains = jnp.stack([jnp.linspace(4.0, 12.0, 5), jnp.linspace(1.0, 4.0, 5)], axis=1)

    def final(R0, g, scalarize, method=METHODS["RKMK4"]):
        sc = eqx.tree_at(lambda s: s.y0.R, scene, scene.y0.R.at[0].set(R0))
        sc = with_gains(sc, g[0], g[1])
        tr = so3jax.simulate(sc, method, 0.05, 16, save_every=16, scalarize=scalarize)
        return tr.R[-1], tr.Omega[-1]

    outs = [jax.jit(jax.vmap(lambda r, g: final(r, g, s)))(R0s, gains) for s in (False, True)]
    for x, y in zip(*outs, strict=True):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=0, atol=1e-14)

    # Gradients through a scalarized scan compile slowly (about 30 s for RKMK4 on
    # 2 cores: XLA sees thousands of scalar operations), so Lie–Euler here.
    def cost(g, scalarize):
        R, W = final(R0s[0], g, scalarize, so3jax.LieEuler())
        return jnp.sum(so3jax.attitude_error_function(R, jnp.eye(3))) + jnp.sum(W**2)

    g0 = jnp.array([8.0, 2.5])
    grad = jax.jit(jax.grad(cost), static_argnums=1)
    ga, gb = grad(g0, False), grad(g0, True)
    np.testing.assert_allclose(np.asarray(gb), np.asarray(ga), rtol=1e-11, atol=1e-14)
    h = 1e-5  # and both against central differences
    c = jax.jit(lambda g: cost(g, True))
    fd = [(c(g0.at[i].add(h)) - c(g0.at[i].add(-h))) / (2 * h) for i in range(2)]
    np.testing.assert_allclose(np.asarray(gb), np.asarray(fd), rtol=1e-6)


def test_scalarized_failure_status_matches():
    scene = so3jax.scenes.seed()
    a = _run(scene, so3jax.RKMK4(), False, n=400, dt=1.5)  # far past stability: blows up
    b = _run(scene, so3jax.RKMK4(), True, n=400, dt=1.5)
    assert int(a.status.code) != 0
    assert (int(b.status.code), int(b.status.step)) == (int(a.status.code), int(a.status.step))
    np.testing.assert_array_equal(np.isnan(np.asarray(b.R)), np.isnan(np.asarray(a.R)))


def test_scalarize_general_function():
    """Reductions, dot_general with batch dims, concatenate, cond, iota: same values."""

    def f(A, v, flag):
        B = jnp.einsum("bij,bjk->bik", A, A) + jnp.eye(3)
        w = jnp.concatenate([v, jnp.max(A, axis=(1, 2)), jnp.arange(2.0)])
        y = jax.lax.cond(flag > 0, lambda x: jnp.sin(x), lambda x: x**2, w)
        return jnp.sum(B, axis=0) @ v[:3] + jnp.sum(y), jnp.abs(v[:2]) * 2.0 + B[0, 0, 0]

    A = jax.random.normal(jax.random.key(0), (2, 3, 3))
    v = jax.random.normal(jax.random.key(1), (4,))
    for flag in (1.0, -1.0):
        ref = f(A, v, flag)
        run = scalarize(f, A, v, flag)
        try:
            out = run(to_components(A), to_components(v), to_components(flag))
        except ScalarizeError as e:  # pragma: no cover - would be a regression
            pytest.fail(str(e))
        for r, o in zip(ref, out, strict=True):
            np.testing.assert_allclose(np.asarray(from_components(o)), np.asarray(r), atol=1e-12)


def test_scalarize_reductions_over_an_empty_axis():
    """A reduction over an empty axis (a sum over ``P[2:]`` of two parameters) is the
    reduction's identity, as in JAX; the scalarizer raised "reduce() of empty iterable"."""

    def f(x, n):
        e, ei = x[:0], n[:0]
        return (
            jnp.sum(e) + x[0],
            jnp.prod(e),
            jnp.max(e, initial=-jnp.inf),
            jnp.min(e, initial=jnp.inf),
            jnp.max(ei, initial=jnp.iinfo(n.dtype).min),
            jnp.all(e > 0),
            jnp.any(e > 0),
            jnp.sum(x.reshape(3, 1)[:, :0], axis=1),
            jnp.max(x > 0),  # reduce_max of booleans
            jnp.min(e > 0, initial=True),  # over an empty boolean axis: its identity
        )

    x, n = jnp.array([1.5, -2.0, 0.5]), jnp.array([3, 1], jnp.int32)
    ref = f(x, n)
    out = scalarize(f, x, n)(to_components(x), to_components(n))
    for r, o in zip(ref, out, strict=True):
        o = np.asarray(from_components(o))
        assert o.dtype == r.dtype and o.shape == r.shape
        np.testing.assert_array_equal(o, np.asarray(r))


def test_scalarize_rejects_unsupported_primitives():
    def f(x):
        return jnp.sort(x)

    with pytest.raises(ScalarizeError, match="sort"):
        scalarize(f, jnp.ones(3))(to_components(jnp.ones(3)))
    with pytest.raises(ValueError, match="fixed steps"):
        so3jax.simulate(so3jax.scenes.seed(), so3jax.RKMK45(), t1=1.0, rtol=1e-6, scalarize=True)


def test_scalarized_compensated_matches():
    scene = so3jax.scenes.seed()
    kw = dict(save_every=20, compensated=True)
    a = so3jax.simulate(scene, so3jax.RKMK4(coords="cayley"), 0.02, 60, **kw)
    b = so3jax.simulate(scene, so3jax.RKMK4(coords="cayley"), 0.02, 60, scalarize=True, **kw)
    np.testing.assert_allclose(np.asarray(b.R), np.asarray(a.R), rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(b.Omega), np.asarray(a.Omega), rtol=0, atol=1e-14)


def test_unsupported_step_falls_back_with_a_warning():
    """A method whose step loops (`fori_loop`) cannot be scalarized: same result, a warning."""

    class Looping(so3jax.AbstractLieSolver):
        @property
        def order(self):
            return 1

        def step(self, scene, t, y, h):
            def body(i, y):
                return so3jax.LieEuler().step(scene, t + i * h / 2, y, h / 2)[0]

            return jax.lax.fori_loop(0, 2, body, y), jnp.array(False)

    scene = so3jax.scenes.seed()
    a = so3jax.simulate(scene, Looping(), 0.02, 20, save_every=20)
    with pytest.warns(UserWarning, match="array program"):
        b = so3jax.simulate(scene, Looping(), 0.02, 20, save_every=20, scalarize=True)
    np.testing.assert_allclose(np.asarray(b.R), np.asarray(a.R), atol=1e-15)


def test_fusion_cuts_keep_values_and_survive_compilation():
    """Cut programs equal uncut ones; under vmap the cuts stay conditionals in XLA's program.

    A value shared by many consumers (``u``) is what XLA would recompute in each;
    the cut must keep it as a buffer (a ``conditional`` in the compiled program),
    not vanish into a ``select`` or a forwarded operand.
    """
    from so3jax._engine.passes.cuts import cut_index
    from so3jax._engine.passes.scalarize import flat_program

    def fn(x):
        u = x[0] * x[1] + x[2] * x[0] - x[1] * x[2] + 1.5 * x[0] * x[0]
        u = u * u + x[1] - 0.25 * u * x[2]
        return jnp.stack([u * x[0], u * x[1], u * x[2], u + 1.0])

    ex = jnp.array([0.3, -0.7, 1.1])
    plain, _ = flat_program(fn, ex)
    xs = jax.random.normal(jax.random.PRNGKey(0), (64, 3))

    def batched(xs, cut):
        index = cut_index(xs) if cut else None
        run, _ = flat_program(fn, ex, index)
        comps = [xs[:, i] for i in range(3)]
        return jax.vmap(lambda *c: jnp.stack(run(list(c))))(*comps)

    cut = jax.jit(lambda xs: batched(xs, True))
    ref = jax.vmap(fn)(xs)
    np.testing.assert_allclose(np.asarray(cut(xs)), np.asarray(ref), rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(
        np.asarray(jnp.stack(plain(list(ex)))), np.asarray(fn(ex)), rtol=1e-15
    )
    assert "cond[" in str(jax.make_jaxpr(cut)(xs))
    assert "conditional(" in cut.lower(xs).compile().as_text()

    # the index stays unbatched under nested vmap, so the cuts stay conditionals
    def inner(x):
        run, _ = flat_program(fn, ex, cut_index(x))
        return jnp.stack(run([x[0], x[1], x[2]]))

    nested = jax.jit(jax.vmap(jax.vmap(inner)))
    xs3 = xs.reshape(8, 8, 3)
    np.testing.assert_allclose(
        np.asarray(nested(xs3)), np.asarray(ref).reshape(8, 8, 4), rtol=1e-14, atol=1e-14
    )
    assert "conditional(" in nested.lower(xs3).compile().as_text()
    # a NaN in the data picks the other identity branch: still the same values
    xs_nan = xs.at[0, 0].set(jnp.nan)
    out = np.asarray(cut(xs_nan))
    np.testing.assert_allclose(out[1:], np.asarray(ref[1:]), rtol=1e-14, atol=1e-14)


def test_settle_batched_reaches_the_scan_fixed_point_and_keeps_shared_values():
    """Carry components are batched up front exactly where a loop would batch them.

    Under `vmap`, ``a`` is batched; ``c`` depends on it after one step and ``b`` after
    two (JAX's scan would batch its body three times to find that); ``d`` never does
    and must stay unbatched (like a reference attitude shared by a batch).
    """
    from so3jax._engine.passes import scalarize as sc

    def step(x):
        a, b, c, d = x
        return (0.5 * a + 1.0, b + c * c, c + jnp.sin(a), 2.0 * d - 1.0)

    ex = tuple(jnp.asarray(v) for v in (1.0, 2.0, 3.0, 4.0))
    index = jnp.asarray(0, jnp.int32)  # a cut index: the cut path of flat_program
    run, _ = sc.flat_program(step, ex, index, cut_cone=2)

    def loop(a, one, settle):
        flat = sc.split((a, *ex[1:]))
        if settle:
            flat = sc.settle_batched(run, flat, [True, False, False, False], one)
        return jax.lax.scan(lambda f, _: (run(f), None), flat, None, length=5)[0]

    flat = sc.split(ex)
    assert sc.batched_components(run, flat, [True, False, False, False]) == [1, 1, 1, 0]
    assert sc.batched_components(run, flat, [False, False, False, True]) == [0, 0, 0, 1]
    plain_run, _ = sc.flat_program(step, ex)  # no cuts: nothing to settle
    assert sc.batched_components(plain_run, flat, [True] * 4) is None
    A = jnp.linspace(0.1, 0.9, 6)
    one = jnp.zeros(6, jnp.int32)
    got = jax.vmap(lambda a, o: loop(a, o, True))(A, one)
    plain = jax.vmap(lambda a, o: loop(a, o, False))(A, one)
    for g, p in zip(got, plain, strict=True):
        np.testing.assert_array_equal(g, p)
    x = (A, *(jnp.full(6, v) for v in ex[1:]))  # a Python loop of the step
    for _ in range(5):
        x = step(x)
    for g, r in zip(got, x, strict=True):
        np.testing.assert_allclose(g, r, rtol=1e-14)
    jaxpr = jax.make_jaxpr(jax.vmap(lambda a, o: loop(a, o, True)))(A, one)
    (scan,) = [e for e in jaxpr.eqns if e.primitive.name == "scan"]
    carry = [v.aval.shape for v in scan.outvars]
    assert carry == [(6,), (6,), (6,), ()], carry  # batched once, d still shared


def test_settle_batched_keeps_values_from_an_outer_jit_unbatched():
    """A value the step closes over from an outer ``jit`` is not batched by the ``vmap``
    inside it: a carry component that depends only on it stays shared (JAX 0.10 has no
    ``batching.not_mapped``, and every traced constant used to count as batched)."""
    from so3jax._engine.passes import scalarize as sc

    seen = []

    def outer(s, A, one):
        def step(x):
            a, d = x
            return (0.5 * a + s, s * d - 1.0)  # d never meets the batched a

        ex = (jnp.asarray(1.0), jnp.asarray(4.0))
        run, _ = sc.flat_program(step, ex, jnp.asarray(0, jnp.int32), cut_cone=2)
        seen.append(sc.batched_components(run, sc.split(ex), [True, False]))

        def loop(a, o):
            flat = sc.settle_batched(run, [a, ex[1]], [True, False], o)
            return jax.lax.scan(lambda f, _: (run(f), None), flat, None, length=3)[0]

        return jax.vmap(loop)(A, one)

    A, one = jnp.linspace(0.1, 0.9, 4), jnp.zeros(4, jnp.int32)
    a3, d3 = jax.jit(outer)(0.5, A, one)
    assert seen == [[1, 0]], seen
    jaxpr = jax.make_jaxpr(outer)(0.5, A, one)
    (vm,) = [e for e in jaxpr.eqns if e.primitive.name == "scan"]
    assert [v.aval.shape for v in vm.outvars] == [(4,), ()]  # d computed once
    d = 4.0
    for _ in range(3):
        d, A = 0.5 * d - 1.0, 0.5 * A + 0.5
    np.testing.assert_allclose(a3, A, rtol=1e-14)
    np.testing.assert_allclose(d3, d, rtol=1e-14)


def test_fusion_cut_branches_are_traced_once_per_operand_types():
    """Cuts at the same operand types share their branch jaxprs (`_cut_branches`); the
    values pass through for index 0 and 1, and the never-taken branch gives zeros."""
    from so3jax._engine.passes import cuts

    cuts._cut_branches.cache_clear()

    def two_cuts(x, index):
        a = cuts.fusion_cut([x, 2.0 * x, x > 0.0], index)
        b = cuts.fusion_cut([a[0] + 1.0, a[1], a[2] & (x < 1.0)], index)
        return b

    f = jax.jit(two_cuts)
    x = jnp.asarray(0.5, jnp.float64)  # strongly typed: both cuts at the same types
    for i in (0, 1):
        out = f(x, jnp.asarray(i, jnp.int32))
        assert [float(v) for v in out] == [1.5, 1.0, 1.0]
    info = cuts._cut_branches.cache_info()
    assert (info.misses, info.hits) == (1, 1), info
    zeros = f(x, jnp.asarray(2, jnp.int32))
    assert [float(v) for v in zeros] == [0.0, 0.0, 0.0]
    assert zeros[2].dtype == jnp.bool_


def test_array_cuts_keep_values_and_derivatives(count_cuts):
    """`array_cut` and `derivative_cut` change no value or derivative (jvp, grad, Hessian,
    under vmap); on the CPU an `array_cut` is a conditional in XLA's program, batched or
    not, a `derivative_cut` one only where differentiated; the scalarizer drops both;
    the probe's index stays unbatched, so a shared operand stays unbatched."""
    from so3jax._engine.passes import cuts, scalarize as sc

    def body(x, cut, deriv):
        u = jnp.sin(x) * x[::-1] + 0.5 * x * x
        if cut:
            (u,) = cuts.array_cut(cuts.array_cut_index(x), u)
        if deriv:
            (u,) = cuts.derivative_cut(u)
        return jnp.sum(u * u * x) + u[0] * u[1]

    x = jnp.array([0.3, -0.7, 1.1])
    xs = jax.random.normal(jax.random.PRNGKey(1), (5, 3))
    plain = functools.partial(body, cut=False, deriv=False)
    for cut, deriv in ((True, False), (False, True), (True, True)):
        f = functools.partial(body, cut=cut, deriv=deriv)
        for t, ref in (
            (jax.jit(f), plain),
            (jax.jit(jax.grad(f)), jax.grad(plain)),
            (jax.jit(jax.hessian(f)), jax.hessian(plain)),
            (
                lambda x, f=f: jax.jvp(f, (x,), (x[::-1],))[1],
                lambda x: jax.jvp(plain, (x,), (x[::-1],))[1],
            ),
        ):
            np.testing.assert_allclose(np.asarray(t(x)), np.asarray(ref(x)), rtol=1e-14)
        got = jax.jit(jax.vmap(jax.grad(f)))(xs)
        ref = jax.vmap(jax.grad(plain))(xs)
        np.testing.assert_allclose(np.asarray(got), np.asarray(ref), rtol=1e-14)
        n_fwd = count_cuts(jax.make_jaxpr(f)(x).jaxpr)
        n_jvp = count_cuts(jax.make_jaxpr(lambda x, f=f: jax.jvp(f, (x,), (x,)))(x).jaxpr)
        assert n_fwd == (1 if cut else 0)
        assert n_jvp == (1 if cut else 0) + (1 if deriv else 0)
        assert "conditional(" in jax.jit(jax.vmap(jax.grad(f))).lower(xs).compile().as_text()
        # the scalarizer drops them: its programs place their own cuts
        jvp, _ = sc.flat_program(lambda x, f=f: jax.jvp(f, (x,), (x,)), x)
        assert "cond[" not in str(jax.make_jaxpr(jvp)(sc.split(x)))

    def pair(a, b):  # a cut over a batched and a shared operand
        return cuts.array_cut(cuts.array_cut_index(a), a * 2.0, b * 3.0)

    jaxpr = jax.make_jaxpr(pair)(x, x).jaxpr
    assert sc.batched_outputs(jaxpr, [True, False]) == [True, False]
    a, b = jax.vmap(pair, in_axes=(0, None), out_axes=(0, None))(xs, x)  # b: unbatched
    np.testing.assert_allclose(np.asarray(a), 2.0 * np.asarray(xs), rtol=1e-15)
    np.testing.assert_allclose(np.asarray(b), 3.0 * np.asarray(x), rtol=1e-15)


def test_values_consumed_by_batched_columns_are_cut():
    """A value that a column-batched operation consumes is cut from a cone of
    the policy's ``column_cut_cone`` operations (XLA would recompute it once per column):
    with the
    inputs' ``columns`` flags, not without; values unchanged, the columns vmapped."""
    from so3jax._engine.passes.cuts import cut_index
    from so3jax._engine.passes.scalarize import flat_program
    from so3jax._engine.policy import current

    column_cut_cone = current().column_cut_cone

    def fn(x):  # x[:2] primal, x[2] a tangent column
        p = x[0] * x[1] + x[0] - x[1] * x[1] + 0.5 * x[0]  # a cone of 6 operations, one use
        q = x[0] + 1.0  # one operation
        return jnp.stack([p * x[2], q * x[2], x[0] - x[1]])

    assert 1 < column_cut_cone <= 6
    ex = jnp.array([0.3, -0.7, 1.1])
    xs = jax.random.normal(jax.random.PRNGKey(1), (64, 3))
    cols = jax.random.normal(jax.random.PRNGKey(2), (2, 64))

    def run(columns):
        def one(col):
            prog, _ = flat_program(fn, ex, cut_index(xs), columns=columns)
            return jnp.stack(prog([xs[:, 0], xs[:, 1], col]))

        return jax.vmap(one)(cols)

    def cuts(columns):
        eqns = jax.make_jaxpr(lambda: run(columns))().eqns
        cond = [e for e in eqns if e.primitive.name == "cond"]
        return sum(len(e.invars) - 1 for e in cond)  # values through a cut

    assert cuts([False, False, False]) == 0
    assert cuts([False, False, True]) == 1  # p, not q
    ref = jax.vmap(lambda c: jax.vmap(fn)(jnp.stack([xs[:, 0], xs[:, 1], c], 1)).T)(cols)
    out = run([False, False, True])
    np.testing.assert_allclose(np.asarray(out), np.asarray(ref), rtol=1e-14, atol=1e-14)
