"""The ``"unroll"`` pass (small reductions written out term by term, so derivative loops can be
hoisted) equals the reference.

Proved as every pass is: `_cases.assert_alone_equals_reference` under every transform and
dtype, and the plan (`so3jax.explain`) shows the pass acting.
"""

import _cases as C
import pytest


@pytest.mark.parametrize("dtype", C.DTYPES)
@pytest.mark.parametrize("case", C.alone("unroll"))
def test_alone_equals_reference(case, dtype):
    C.assert_alone_equals_reference("unroll", case, dtype)


@pytest.mark.parametrize("case", ("seed",))
def test_plan_shows_the_pass(case):
    plan = C.plan(case, "grad", C.NEEDS["unroll"] | {"unroll"})
    assert any(e["hoisted"] and e.get("unrolled") for e in plan.of("hoisting")), plan
    off = C.plan(case, "grad", C.NEEDS["unroll"])
    assert off.passes == tuple(sorted(C.NEEDS["unroll"]))
