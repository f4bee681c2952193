"""The ``"cuts"`` pass (fusion cuts where XLA on CPU would recompute shared values) equals the
reference.

Proved as every pass is: `_cases.assert_alone_equals_reference` under every transform and
dtype, and the plan (`so3jax.explain`) shows the pass acting.
"""

import _cases as C
import pytest


@pytest.mark.parametrize("dtype", C.DTYPES)
@pytest.mark.parametrize("case", C.alone("cuts"))
def test_alone_equals_reference(case, dtype):
    C.assert_alone_equals_reference("cuts", case, dtype)


@pytest.mark.parametrize("case", ("seed",))
def test_plan_shows_the_pass(case):
    plan = C.plan(case, "vmap", C.NEEDS["cuts"] | {"cuts"})
    assert any(e.get("cuts") for e in plan.of("layout")), plan
    off = C.plan(case, "vmap", C.NEEDS["cuts"])
    assert off.passes == tuple(sorted(C.NEEDS["cuts"]))
