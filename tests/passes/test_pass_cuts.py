"""The ``"cuts"`` pass (fusion cuts where XLA on CPU would recompute shared values) equals the
reference.

Under ``jit``, ``vmap``, ``grad``, ``jacfwd`` and ``jax.hessian`` (`_cases`), in float64
and float32: the pass alone (with what it needs, `_cases.NEEDS`) against every pass off,
on the steps of `_cases.alone`; ``test_passes_together.py`` runs every pass together on
the steps of `_cases.TOGETHER`. The pass changes the program compared (`_cases.assert_acts`), so the
comparison is not of a program with itself, and the plan (`so3jax.explain`) shows it
acting.
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
