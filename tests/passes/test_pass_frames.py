"""The ``"frames"`` pass (attitude tangents as three numbers in the Jacobian programs) equals the
reference.

Proved as every pass is: `_cases.assert_alone_equals_reference` under every transform and
dtype, and the plan (`so3jax.explain`) shows the pass acting.
"""

import _cases as C
import pytest


@pytest.mark.parametrize("dtype", C.DTYPES)
@pytest.mark.parametrize("case", C.alone("frames"))
def test_alone_equals_reference(case, dtype):
    C.assert_alone_equals_reference("frames", case, dtype)


@pytest.mark.parametrize("case", ("seed", "lgvi"))
def test_plan_shows_the_pass(case):
    plan = C.plan(case, "grad", C.NEEDS["frames"] | {"frames"})
    # two rotations (body and reference) in the carry; LGVI's tangent comes out dense
    rotations = [e["rotations"] for e in plan.of("frames")]
    assert rotations and (max(rotations) == 0 if case == "lgvi" else max(rotations) > 0), plan
    off = C.plan(case, "grad", C.NEEDS["frames"])
    assert off.passes == tuple(sorted(C.NEEDS["frames"]))
