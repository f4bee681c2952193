"""The ``"scalarize"`` pass (a batch as a structure-of-arrays program of scalar components) equals
the reference.

Proved as every pass is: `_cases.assert_alone_equals_reference` under every transform and
dtype, and the plan (`so3jax.explain`) shows the pass acting.
"""

import _cases as C
import pytest


def fresh(fn):
    """``fn`` as a new function object: JAX traces it anew, under the active policy, where
    it would reuse its trace of ``fn`` (`so3jax._engine.policy`)."""
    return lambda *args: fn(*args)


@pytest.mark.parametrize("dtype", C.DTYPES)
@pytest.mark.parametrize("case", C.alone("scalarize"))
def test_alone_equals_reference(case, dtype):
    C.assert_alone_equals_reference("scalarize", case, dtype)


@pytest.mark.parametrize("case", ("seed",))
def test_plan_shows_the_pass(case):
    plan = C.plan(case, "grad", C.NEEDS["scalarize"] | {"scalarize"})
    layouts = plan.of("layout")
    assert any(e["layout"] == "scalarized" and e["program"] == "jacobian" for e in layouts), plan
    batch = C.plan(case, "vmap", {"scalarize"}).of("layout")
    assert any(e["layout"] == "scalarized" and e["program"] == "run" for e in batch), batch
    off = C.plan(case, "grad", C.NEEDS["scalarize"])
    assert off.passes == tuple(sorted(C.NEEDS["scalarize"]))


def test_dynamic_slice_reads_a_table():
    """``lax.dynamic_slice`` over components equals JAX's: constant, computed and batched
    starts, slices longer than one, and starts clamped into the table as JAX clamps them."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from so3jax._engine.passes import scalarize as S

    table = jnp.arange(15.0).reshape(5, 3) ** 1.5

    def f(tab, i):
        return jax.lax.dynamic_slice(tab, (i, jnp.int32(1)), (2, 2)), tab[i]

    run = S.scalarize(f, table, jnp.int32(0))
    comps = S.to_components(table)
    for i in (-3, 0, 2, 3, 4, 9):  # concrete starts fold to slices
        got = run(comps, S._const(np.int32(i)))
        want = f(table, jnp.int32(i))
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(S.from_components(g), w)

    traced = jax.jit(lambda i: [S.from_components(g) for g in run(comps, S.to_components(i))])
    for i in (-3, 0, 3, 4, 9):  # computed starts select
        for g, w in zip(traced(jnp.int32(i)), f(table, jnp.int32(i)), strict=True):
            np.testing.assert_array_equal(g, w)

    starts = jnp.array([0, 4, 2, 7], jnp.int32)  # one start per run, tables per run
    tables = table[None] * jnp.arange(1.0, 5.0)[:, None, None]
    batched = jax.vmap(
        lambda tab, i: [S.from_components(g) for g in run(S.to_components(tab), S.to_components(i))]
    )
    for g, w in zip(batched(tables, starts), jax.vmap(f)(tables, starts), strict=True):
        np.testing.assert_array_equal(g, w)


def test_gust_batch_is_scalarized():
    """A batch of quadrotors in `so3jax.Gust`s (the wind read from each run's path at a
    computed index) is scalarized, and equals the reference. The path, longer than the
    policy's ``scalarize_table_max``, stays whole (`scalarize._Table`) in the forward
    program; the table read's derivatives are `test_table_read_under_every_transform`'s."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    import so3jax as s
    from so3jax._engine import policy

    dt, n = 0.0025, 6
    base = s.scenes.quadrotor_recovery(control_period=dt)
    keys = jax.random.split(jax.random.key(5), C.B)
    R0s = s.random_rotation(jax.random.key(6), (C.B,))

    def batch(mu):  # traced anew under each policy (`fresh`)
        def one(key, R0):
            gust = s.Gust(0.0, 1.5, 0.001, duration=n * dt, key=key)  # 301 points
            gust = eqx.tree_at(lambda g: g.mean, gust, mu)
            sc = s.scenes.quadrotor(
                base.vehicle.mass, base.vehicle.body, base.gains, base.reference,
                control_period=dt, drag=2.0, wind=gust,
            )  # fmt: skip
            return s.simulate(sc, s.LieEuler(), dt, n, n // 2, R0=R0).extras["v"]

        return jax.vmap(one)(keys, R0s)

    def gust_points(mu):
        return s.Gust(0.0, 1.5, 0.001, duration=n * dt, key=0).path.shape[0]

    mu = jnp.array([4.0, -1.0, 0.5])
    out = {}
    for passes in (frozenset(), frozenset({"scalarize"})):
        with policy.using(C.SMALL, passes=passes):
            plan = s.explain(fresh(batch), mu).of("layout")
            out[passes] = np.asarray(jax.jit(fresh(batch))(mu))
        assert ({e["layout"] for e in plan} == {"scalarized"}) == bool(passes), plan
    ref, got = out[frozenset()], out[frozenset({"scalarize"})]
    assert gust_points(mu) > C.SMALL.scalarize_table_max
    assert np.ptp(ref[:, -1, 0]) > 0.01  # the runs' gusts differ
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-14)


def test_table_read_under_every_transform():
    """A loop whose step reads a per-run table at an index computed from its state (as a
    `Gust` reads its path) equals the reference under ``jit``, ``vmap``, ``grad``,
    ``jacfwd`` and ``jax.hessian``, scalarized."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import so3jax as s
    from so3jax._engine import policy, run

    tables = jnp.sin(jnp.arange(C.B * 8 * 2.0)).reshape(C.B, 8, 2)

    def step(P, c):
        (k, table), (x, i) = P, c
        w = k[1] * table[jnp.clip(i, 0, 7)]
        return x + 0.1 * (k[0] * w - k[1] * x * x), i + 1

    def observe(P, c):
        return jnp.sum(c[0] ** 2), c[0]

    def go(k, table):
        c0 = (jnp.zeros(2), jnp.array(0, jnp.int32))
        return run(step, observe, (k, table), c0, C.N, C.SAVE)[0]

    def mean(k):
        return jnp.mean(jax.vmap(lambda t: jnp.sum(go(k, t)[0]))(tables))

    def transforms():  # traced anew under each policy (`fresh`)
        m = fresh(mean)
        return {"jit": lambda k: go(k, tables[0]), "vmap": m, "grad": jax.grad(m),
                "jacfwd": jax.jacfwd(m), "hessian": jax.hessian(m)}  # fmt: skip

    out = {}
    for passes in (frozenset(), frozenset({"scalarize"})):
        with policy.using(C.SMALL, passes=passes):
            fns = transforms()
            out[passes] = {t: jax.tree.map(np.asarray, jax.jit(f)(C.K0)) for t, f in fns.items()}
            plan = s.explain(fresh(mean), C.K0).of("layout")
        assert ({e["layout"] for e in plan} == {"scalarized"}) == bool(passes), plan
    for t in fns:
        for a, b in zip(jax.tree.leaves(out[frozenset({"scalarize"})][t]),
                        jax.tree.leaves(out[frozenset()][t]), strict=True):  # fmt: skip
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14, err_msg=t)


def test_a_long_table_runs_the_array_program():
    """A table longer than the policy's ``scalarize_table_max`` (each entry would be a
    component the loop carries) is not scalarized: the batch runs the array program and
    the plan says why; at the limit it is scalarized."""
    import jax
    import jax.numpy as jnp

    import so3jax as s
    from so3jax._engine import policy, run

    tables = jnp.cos(jnp.arange(C.B * 8 * 2.0)).reshape(C.B, 8, 2)

    def step(P, c):
        x, i = c
        return x + 0.1 * P[jnp.clip(i, 0, 7)], i + 1

    def mean(tables):
        def one(table):
            c0 = (jnp.zeros(2), jnp.array(0, jnp.int32))
            out = run(step, lambda P, c: (c[0],), table, c0, 4, 2)
            return jnp.sum(out[0][0])

        return jnp.mean(jax.vmap(one)(tables))

    for limit, layout in ((7, "array"), (8, "scalarized")):
        with policy.using(C.SMALL.replace(scalarize_table_max=limit)):
            plan = s.explain(mean, tables).of("layout")
        assert [e["layout"] for e in plan] == [layout], plan
        if layout == "array":
            assert "scalarize_table_max is 7" in plan[0]["why"], plan


def test_a_closed_over_table_stays_whole():
    """A large constant closed over by the scalarized function (`scalarize._Table`) is read
    by ``dynamic_slice`` whole and, used otherwise, by its components: both equal JAX's."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from so3jax._engine.passes import scalarize as S

    big = jnp.sin(jnp.arange(400.0)).reshape(200, 2)
    assert S.is_table(big)

    def f(i, x):
        row = jax.lax.dynamic_slice(big, (i, jnp.int32(0)), (2, 2))
        return row * x + big[7, 1], jnp.sum(big[:3] * x)

    run = S.scalarize(f, jnp.int32(0), jnp.float64(1.0))
    go = jax.jit(
        lambda i, x: [S.from_components(o) for o in run(S.to_components(i), S.to_components(x))]
    )
    for i in (-4, 0, 117, 199, 500):  # to round-off: XLA may fuse `row * x + c` into an FMA
        for got, want in zip(go(jnp.int32(i), 1.5), f(jnp.int32(i), 1.5), strict=True):
            np.testing.assert_allclose(got, want, rtol=1e-15, atol=1e-15)
