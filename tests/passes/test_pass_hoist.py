"""The ``"hoist"`` pass (each loop one kernel on a CPU) equals the reference.

Under ``jit``, ``vmap``, ``grad``, ``jacfwd`` and ``jax.hessian`` (`_cases`): the pass alone
(with what it needs, `_cases.NEEDS`) against every pass off, on the steps of `_cases.ALONE`;
``test_passes_together.py`` runs every pass together on the
steps of `_cases.TOGETHER`. The plan (`so3jax.explain`) shows the pass acting, so the
comparison is not of a program with itself.
"""

import _cases as C
import pytest


@pytest.mark.parametrize("case", C.ALONE)
def test_alone_equals_reference(case):
    C.assert_equal_to_reference(C.NEEDS["hoist"] | {"hoist"}, case)


@pytest.mark.parametrize("case", ("seed",))
def test_plan_shows_the_pass(case):
    plan = C.plan(case, "vmap", C.NEEDS["hoist"] | {"hoist"})
    assert plan.of("hoisting") and all(e["hoisted"] for e in plan.of("hoisting")), plan
    off = C.plan(case, "vmap", C.NEEDS["hoist"])
    assert off.passes == tuple(sorted(C.NEEDS["hoist"]))
