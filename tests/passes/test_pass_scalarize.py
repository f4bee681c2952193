"""The ``"scalarize"`` pass (a batch as a structure-of-arrays program of scalar components) equals
the reference.

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
    C.assert_equal_to_reference(C.NEEDS["scalarize"] | {"scalarize"}, case)


@pytest.mark.parametrize("case", ("seed",))
def test_plan_shows_the_pass(case):
    plan = C.plan(case, "grad", C.NEEDS["scalarize"] | {"scalarize"})
    layouts = plan.of("layout")
    assert any(e["layout"] == "scalarized" and e["program"] == "jacobian" for e in layouts), plan
    batch = C.plan(case, "vmap", {"scalarize"}).of("layout")
    assert any(e["layout"] == "scalarized" and e["program"] == "run" for e in batch), batch
    off = C.plan(case, "grad", C.NEEDS["scalarize"])
    assert off.passes == tuple(sorted(C.NEEDS["scalarize"]))
