"""The version gate of JAX's internals (`so3jax._engine._jax`): on a JAX release outside
`TESTED`, the engine runs its reference programs (the checkpointed ``lax.scan`` and
JAX's own autodiff), with the same results, and warns once; on a jaxlib outside
`HOIST_TESTED`, loops are not hoisted, with the same results, and it warns once."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import so3jax
from so3jax._engine import _jax, policy
from so3jax._engine.passes import hoist

SC = so3jax.scenes.seed()
M = so3jax.RKMK4()
R = so3jax.random_rotation(jax.random.PRNGKey(0), (2,))
W = jnp.zeros((2, 3))
K = jnp.array([8.81, 2.54])


def _cost(k):
    return so3jax.expected_cost(SC, k[0], k[1], R, W, M, 1e-2, 10)


def test_the_installed_jax_is_tested():
    assert _jax.supported(), f"JAX {jax.__version__}: add it to TESTED once the suite passes"


def test_an_untested_release_takes_the_reference_path(monkeypatch):
    fast = so3jax.explain(jax.grad(_cost), K)
    assert [e["program"] for e in fast.of("loop")] == ["auto"]
    value, grad = jax.value_and_grad(_cost)(K)

    monkeypatch.setattr(_jax, "TESTED", frozenset())
    _jax.warn_reference_path.cache_clear()
    with pytest.warns(UserWarning, match="reference path"):
        plan = so3jax.explain(jax.grad(_cost), K)
    assert [e["program"] for e in plan.of("loop")] == ["autodiff"]
    assert not plan.of("derivative")  # JAX's own autodiff: no engine rule ran
    assert {e["layout"] for e in plan.of("layout")} <= {"array"}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once per process: no second warning
        ref_value, ref_grad = jax.value_and_grad(_cost)(K)
    np.testing.assert_allclose(ref_value, value, rtol=1e-12)
    np.testing.assert_allclose(ref_grad, grad, rtol=1e-10)
    _jax.warn_reference_path.cache_clear()


def test_a_jaxlib_not_verified_for_hoisting_runs_loops_as_xla_builds_them(monkeypatch):
    """Where the ``"hoist"`` pass is held back (`policy.HOIST_HELD_BACK`), the plan says why,
    the first run warns once, and the values are the hoisted runs'."""
    fast = so3jax.explain(jax.grad(_cost), K)
    assert any(e["hoisted"] for e in fast.of("hoisting")) == policy.DEFAULT.on("hoist")
    value, grad = jax.value_and_grad(_cost)(K)

    monkeypatch.setattr(policy, "HOIST_HELD_BACK", True)
    hoist.warn_held_back.cache_clear()
    with policy.using(passes=policy.PASSES - {"hoist"}):
        with pytest.warns(UserWarning, match="one kernel"):
            plan = so3jax.explain(jax.grad(_cost), K)
        assert plan.of("hoisting") and not any(e["hoisted"] for e in plan.of("hoisting"))
        assert all("not verified" in e["why"] for e in plan.of("hoisting")), plan
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # once per process
            held_value, held_grad = jax.value_and_grad(_cost)(K)
    np.testing.assert_allclose(held_value, value, rtol=1e-12)
    np.testing.assert_allclose(held_grad, grad, rtol=1e-10)
    hoist.warn_held_back.cache_clear()
