"""Every pass of the engine's policy together equals the reference.

Under ``jit``, ``vmap``, ``grad``, ``jacfwd`` and ``jax.hessian`` (first derivatives only
for LGVI and the quadrotor, `_cases.FIRST_ORDER`), on the steps of `_cases.TOGETHER` (the
seed, LGVI, the quadrotor with its control held and a step containing ``lax.cond``) in
float64, and on those of `_cases.ALONE` in float32: the passes of the default policy (all
of them, or those ``SO3JAX_PASSES`` names) against every pass off. Each pass alone:
``test_pass_<name>.py``.
"""

import _cases as C
import pytest

from so3jax._engine import policy

RUNS = [(case, "float64") for case in C.TOGETHER] + [(case, "float32") for case in C.ALONE]


@pytest.mark.parametrize("case, dtype", RUNS)
def test_default_passes_equal_reference(case, dtype):
    C.assert_equal_to_reference(policy.DEFAULT.passes, case, dtype)
