"""`so3jax.explain`: the engine's documented plan for each kind of call (`so3jax._engine`:
the array program for one run and small batches, the scalarized one from
``batched_layout``'s threshold; the one-pass Jacobian through at most
``forward_jacobian_max`` scalars, JAX's jvp of the checkpointed program through more).
Tracing only: nothing is compiled or run."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import pytest

import so3jax
from so3jax import _engine

SC = so3jax.scenes.seed()
M = so3jax.RKMK4()
N = 8
K = jnp.array([8.81, 2.54])


def _layouts(plan, program):
    return [(e["runs"], e["layout"]) for e in plan.of("layout") if e["program"] == program]


def _strategies(plan):
    return [e["strategy"] for e in plan.of("derivative")]


def _starts(B):
    return so3jax.random_rotation(jax.random.PRNGKey(0), (B,)), jnp.zeros((B, 3))


def test_single_run():
    plan = so3jax.explain(lambda: so3jax.simulate(SC, M, 1e-2, N))
    assert plan.of("loop")[0]["n_steps"] == N
    assert _layouts(plan, "run") == [(1, "array")]
    assert _strategies(plan) == []
    assert "layout" in str(plan)


@pytest.mark.parametrize("B", [4, 16, 4096])
def test_batches(B):
    R, _ = _starts(B)
    plan = so3jax.explain(jax.vmap(lambda R: so3jax.simulate(SC, M, 1e-2, N, R0=R)), R)
    threshold = _engine.policy.batched_layout("run")[0]
    assert _layouts(plan, "run") == [(B, "scalarized" if B >= threshold else "array")]
    # what runs is the batch: no entry of the unbatched trace that `custom_vmap` also makes
    assert all(e["runs"] == B for e in plan.of("hoisting")), plan


def _mean_cost(B):
    R, W = _starts(B)
    return lambda k: so3jax.expected_cost(SC, k[0], k[1], R, W, M, 1e-2, N)


def test_grad_through_two_gains_is_one_pass():
    plan = so3jax.explain(jax.grad(_mean_cost(16)), K)
    assert _strategies(plan) == ["one-pass Jacobian"]
    assert plan.of("derivative")[0]["scalars"] == 2
    assert _layouts(plan, "jacobian")[-1] == (16, "scalarized")


def test_jacfwd_is_one_pass_too():
    plan = so3jax.explain(jax.jacfwd(_mean_cost(2)), K)
    assert _strategies(plan) == ["one-pass Jacobian"]
    assert _layouts(plan, "jacobian")[-1] == (2, "array")


def test_grad_through_twelve_gains_is_the_discrete_adjoint():
    quad = so3jax.scenes.quadrotor_circle()

    def loss(gains):
        traj = so3jax.simulate(eqx.tree_at(lambda s: s.gains, quad, gains), M, 0.0025, N)
        return jnp.sum(traj.extras["e_x"] ** 2)

    gains = jax.tree.map(lambda g: jnp.broadcast_to(g, (3,)), quad.gains)
    n = sum(g.size for g in jax.tree.leaves(gains))
    assert n == 12 > _engine.policy.current().forward_jacobian_max
    plan = so3jax.explain(jax.grad(loss), gains)
    assert _strategies(plan) == ["checkpointed jvp, discrete adjoint"]
    # the 12 gains and what the scene derives from them (the held control at t = 0)
    assert plan.of("derivative")[0]["scalars"] >= 12
    # checkpoints by default; every step's residuals within a budget (`tune`'s, one start)
    assert [e["saved"] for e in plan.of("adjoint")] == ["checkpoints"]
    budget = _engine.policy.current().tune_residual_bytes
    with _engine.policy.using(adjoint_residual_bytes=budget):
        (adjoint,) = so3jax.explain(jax.grad(loss), gains).of("adjoint")
    assert adjoint["saved"] == "residuals" and adjoint["bytes_per_step"] * N <= budget


def test_hessian_differentiates_the_rules_programs():
    plan = so3jax.explain(jax.hessian(_mean_cost(2)), K)
    strategies = _strategies(plan)
    assert strategies[0] == "one-pass Jacobian"
    assert "second derivative" in strategies


def test_nothing_is_recorded_outside_explain():
    from so3jax._engine import plan as _plan

    assert _plan.count() == 0
    _plan.note("layout", program="run", runs=1, layout="array")  # a no-op here
    assert _plan.count() == 0
