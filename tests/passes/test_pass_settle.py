"""The ``"settle"`` pass (each loop starts where JAX's fixed point over its carry ends)
equals the reference.

Under ``jit``, ``vmap``, ``grad``, ``jacfwd`` and ``jax.hessian`` (`_cases`): the pass alone
against every pass off, on the steps of `_cases.ALONE`; ``test_passes_together.py`` runs
every pass together on the steps of `_cases.TOGETHER`. The plan (`so3jax.explain`) shows
the pass acting, so the comparison is not of a program with itself.
"""

import _cases as C
import pytest


@pytest.mark.parametrize("case", C.ALONE)
def test_alone_equals_reference(case):
    C.assert_equal_to_reference(C.NEEDS["settle"] | {"settle"}, case)


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
