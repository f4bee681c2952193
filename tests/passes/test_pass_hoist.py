"""The ``"hoist"`` pass (each loop one kernel on a CPU) equals the reference.

Proved as every pass is: `_cases.assert_alone_equals_reference` under every transform and
dtype, and the plan (`so3jax.explain`) shows the pass acting.
"""

import _cases as C
import hypothesis.strategies as st
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings

from so3jax._engine import policy
from so3jax._engine.programs import _pack, _unpack


@pytest.mark.parametrize("dtype", C.DTYPES)
@pytest.mark.parametrize("case", C.alone("hoist"))
def test_alone_equals_reference(case, dtype):
    C.assert_alone_equals_reference("hoist", case, dtype)


@C.ON_ONE_CPU_DEVICE
@pytest.mark.parametrize("case", ("seed",))
def test_plan_shows_the_pass(case):
    plan = C.plan(case, "vmap", C.NEEDS["hoist"] | {"hoist"})
    assert plan.of("hoisting") and all(e["hoisted"] for e in plan.of("hoisting")), plan
    off = C.plan(case, "vmap", C.NEEDS["hoist"])
    assert off.passes == tuple(sorted(C.NEEDS["hoist"]))


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


@C.ON_ONE_CPU_DEVICE
def test_no_hoisted_loop_makes_an_array_xla_would_split_across_threads():
    """A loop that makes an array of the policy's ``hoist_max_inner`` bytes or more inside
    its body, over the batch, is not hoisted: from 8 MiB XLA's CPU compiler splits an
    operation on it across threads, and the hoisted kernel fails to link
    ``__xla_cpu_runtime_ParallelForkJoin`` (``vmap`` of ``grad`` through a quadrotor's
    gains over 192 runs of 100 steps: the discrete adjoint's segments of 10 steps stack
    about 45 kB of residuals a run). Traced only: compiling the failing program takes
    20 s. The input leaves pass ``hoist_max_bytes``, checked first: the reason names
    ``hoist_max_inner``."""
    import equinox as eqx
    import jax

    import so3jax as s

    scene = s.scenes.quadrotor_circle(control_period=0.0025)

    def loss(k_x):
        sc = eqx.tree_at(lambda q: q.gains.k_x, scene, k_x)
        return jnp.sum(s.simulate(sc, s.RKMK4(), 0.0025, 100).extras["e_x"] ** 2)

    k_x = scene.gains.k_x * (1 + 1e-3 * jnp.arange(192))[:, None]
    with policy.using(passes=policy.PASSES):  # (on a jaxlib that holds the pass back too)
        plan = s.explain(jax.vmap(jax.grad(loss)), k_x)
    assert [e["saved"] for e in plan.of("adjoint")] == ["checkpoints"]
    backward = plan.of("hoisting")[-1]  # the backward pass's loop, batched
    assert not backward["hoisted"] and "hoist_max_inner" in backward["why"]
