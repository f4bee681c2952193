"""The ``"hoist"`` pass (each loop one kernel on a CPU) equals the reference.

Under ``jit``, ``vmap``, ``grad``, ``jacfwd`` and ``jax.hessian`` (`_cases`): the pass alone
(with what it needs, `_cases.NEEDS`) against every pass off, on the steps of `_cases.ALONE`;
``test_passes_together.py`` runs every pass together on the
steps of `_cases.TOGETHER`. The plan (`so3jax.explain`) shows the pass acting, so the
comparison is not of a program with itself.
"""

import _cases as C
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings

from so3jax._engine import policy
from so3jax._engine.passes.hoist import called_whole
from so3jax._engine.programs import _pack, _unpack


@pytest.mark.parametrize("case", C.ALONE)
def test_alone_equals_reference(case):
    C.assert_equal_to_reference(C.NEEDS["hoist"] | {"hoist"}, case)


@pytest.mark.parametrize("case", ("seed",))
def test_plan_shows_the_pass(case):
    plan = C.plan(case, "vmap", C.NEEDS["hoist"] | {"hoist"})
    assert plan.of("hoisting") and all(e["hoisted"] for e in plan.of("hoisting")), plan
    off = C.plan(case, "vmap", C.NEEDS["hoist"])
    assert off.passes == tuple(sorted(C.NEEDS["hoist"]))


def _sample(p, x):
    """A computation without loops, with small reductions (written out when hoisted)."""
    r = jnp.sum(jnp.sin(p * x) * x) + jnp.prod(jnp.cos(x[:2]))
    return {"r": r, "v": jnp.cross(x, p * x)}


def _whole(p, x):
    return called_whole(_sample, p, x)


def _r(f):
    return lambda p, x: f(p, x)["r"]


_TRANSFORMS = {
    "jit": lambda f: f,
    "grad": lambda f: jax.grad(lambda p, x: f(p, x)["r"] + jnp.sum(f(p, x)["v"] ** 2)),
    "jacfwd": lambda f: jax.jacfwd(f),
    "vmap": lambda f: jax.vmap(f, in_axes=(0, None)),
    "vmap-grad": lambda f: jax.vmap(jax.grad(_r(f)), in_axes=(0, None)),
    "hessian": lambda f: jax.hessian(_r(f)),
}


@pytest.mark.parametrize("transform", list(_TRANSFORMS))
def test_called_whole_equals_the_function(transform):
    """`called_whole` (a scene's work outside its loops, compiled whole) equals the
    function it calls, under every transform, the batched ones included."""
    x = jnp.array([0.3, -1.2, 0.7])
    p = jnp.linspace(0.5, 2.0, 5) if transform.startswith("vmap") else jnp.array(1.7)
    with policy.using(passes=frozenset({"hoist", "unroll"})):
        got = jax.jit(_TRANSFORMS[transform](_whole))(p, x)
    want = jax.jit(_TRANSFORMS[transform](_sample))(p, x)
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-14)


def test_called_whole_is_compiled_whole_and_only_where_the_policy_says():
    """Staged as one call XLA's older CPU emitter compiles (``xla_cpu_small_call``), its
    derivative too; with the pass off, or outside a trace, it is the function itself."""
    p, x = jnp.array(1.7), jnp.array([0.3, -1.2, 0.7])

    def cost(p, x):
        return _whole(p, x)["r"]

    def hlo(fn):
        return jax.jit(fn).lower(p, x).as_text()

    with policy.using(passes=frozenset({"hoist", "unroll"})):
        on, on_grad = hlo(cost), hlo(jax.grad(cost))
        eager = _whole(p, x)
    with policy.using(passes=frozenset()):
        off = hlo(jax.grad(cost))
    if jax.default_backend() == "cpu" and len(jax.devices()) == 1:
        assert "xla_cpu_small_call" in on and "xla_cpu_small_call" in on_grad
    assert "xla_cpu_small_call" not in off
    np.testing.assert_allclose(eager["r"], _sample(p, x)["r"], rtol=1e-15)


@given(
    st.lists(
        st.tuples(
            st.sampled_from(["float64", "float32", "int32", "bool"]),
            st.lists(st.integers(1, 3), max_size=3),
        ),
        max_size=8,
    )
)
@settings(max_examples=30, deadline=None)
def test_residuals_pack_into_one_vector_per_dtype_and_back(specs):
    """`_pack` (the discrete adjoint's residuals leave its loop as one array per dtype)
    and `_unpack` are inverse, whatever the leaves' shapes and dtypes."""
    rng = np.random.default_rng(len(specs))
    leaves = [jnp.asarray(rng.normal(size=shape) * 5).astype(dtype) for dtype, shape in specs]
    packed, spec = _pack(leaves)
    assert len(packed) == len({x.dtype for x in leaves})
    assert all(a.ndim == 1 for a in packed)
    back = _unpack(packed, spec)
    assert len(back) == len(leaves)
    for a, b in zip(back, leaves, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
