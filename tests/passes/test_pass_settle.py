"""The ``"settle"`` pass (each loop starts where JAX's fixed point over its carry ends)
equals the reference.

Proved as every pass is: `_cases.assert_alone_equals_reference` under every transform and
dtype, and the plan (`so3jax.explain`) shows the pass acting.
"""

import _cases as C
import pytest


@pytest.mark.parametrize("dtype", C.DTYPES)
@pytest.mark.parametrize("case", C.alone("settle"))
def test_alone_equals_reference(case, dtype):
    C.assert_alone_equals_reference("settle", case, dtype)


@pytest.mark.parametrize("case", ("seed",))
def test_plan_shows_the_pass(case):
    """A batch below the scalarized layout's threshold runs the array program: its loops
    start with the run's status batched (the loop would batch it); the Hessian's rule
    starts its carry tangents nonzero."""
    plan = C.plan(case, "vmap", {"settle"})
    assert any(e["what"] == "batched carry" for e in plan.of("settle")), plan
    plan = C.plan(case, "hessian", {"settle"})
    assert any(e["what"] == "carry tangents" for e in plan.of("settle")), plan
    for transform in ("vmap", "hessian"):
        off = C.plan(case, transform, set())
        assert not off.of("settle") and off.passes == (), off
