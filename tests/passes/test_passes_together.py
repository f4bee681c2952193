"""Every pass of the engine's policy together equals the reference.

Under ``jit``, ``vmap``, ``grad``, ``jacfwd`` and ``jax.hessian`` (first derivatives only
for LGVI and the quadrotor, `_cases.FIRST_ORDER`), on the steps of `_cases.TOGETHER` (the
seed, LGVI, the quadrotor with its control held and a step containing ``lax.cond``): the
passes of the default policy (all of them, or those ``SO3JAX_PASSES`` names) against every
pass off. Each pass alone: ``test_pass_<name>.py``.
"""

import _cases as C
import pytest

from so3jax._engine import policy


@pytest.mark.parametrize("case", C.TOGETHER)
def test_default_passes_equal_reference(case):
    C.assert_equal_to_reference(policy.DEFAULT.passes, case)
