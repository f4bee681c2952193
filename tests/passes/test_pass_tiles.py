"""The ``"tiles"`` pass (a batch of Jacobian programs in cache-sized tiles) equals the reference.

Proved as every pass is: `_cases.assert_alone_equals_reference` under every transform and
dtype, and the plan (`so3jax.explain`) shows the pass acting.
"""

import _cases as C
import pytest


@pytest.mark.parametrize("dtype", C.DTYPES)
@pytest.mark.parametrize("case", C.alone("tiles"))
def test_alone_equals_reference(case, dtype):
    C.assert_alone_equals_reference("tiles", case, dtype)


@pytest.mark.parametrize("case", ("seed",))
def test_plan_shows_the_pass(case):
    plan = C.plan(case, "grad", C.NEEDS["tiles"] | {"tiles"})
    assert any(e["program"] == "jacobian" and e["n"] == 2 for e in plan.of("tiles")), plan
    off = C.plan(case, "grad", C.NEEDS["tiles"])
    assert off.passes == tuple(sorted(C.NEEDS["tiles"]))
