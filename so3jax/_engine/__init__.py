"""The execution engine: how every fixed-step run executes.

`simulate`, `rollout_cost` / `expected_cost`, `sweep` and `tune` hand their loop to `run`;
`explain` says what a call executes and why.

How to read it, smallest first:

- `so3jax._engine.loop`: the reference programs, ``lax.scan`` and its checkpointed segments.
- `so3jax._engine.derivatives`: `Autodiff`, `OnePassJacobian`, `CheckpointedAdjoint` and `choose`.
- `so3jax._engine.layout`: the array program for one run, the scalarized one for a batch.
- `so3jax._engine.policy`: every threshold and switch, in one frozen `Policy`.
- `so3jax._engine.passes`: one module per pass (``tests/passes/``, ``benchmarks/ablation.py``).
- `so3jax._engine.programs`: the Jacobian and adjoint programs of one loop.
- `so3jax._engine._jax`: every JAX internal touched, behind a version gate.

Design and measurements: ``docs/engine.md``, ``docs/performance.md``.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import jax

from . import _jax, derivatives, plan as _plan, policy
from .layout import _dual
from .loop import checkpoint_length
from .passes import scalarized
from .plan import Plan, explain
from .programs import Programs

__all__ = ["run", "explain", "Plan", "checkpoint_length", "policy", "derivatives"]

_PROGRAMS = ("auto", "array", "scalar", "autodiff", "adjoint")


def run(
    step: Callable,
    observe: Callable,
    params,
    carry0,
    n_steps: int,
    save_every: int = 1,
    *,
    checkpoint: int | None = None,
    program: str = "auto",
):
    """Step ``carry0`` ``n_steps`` times; observe every ``save_every``-th state.

    **Arguments:**

    - `step`: ``step(params, carry) -> carry``, pure (a carry may hold integer leaves).
    - `observe`: ``observe(params, carry) -> pytree`` of float arrays.
    - `params`: a pytree of arrays; derivatives flow to its float leaves and ``carry0``'s.
    - `n_steps`, `save_every`: Python ints, ``n_steps % save_every == 0``.
    - `checkpoint`: steps per checkpointed segment of the adjoint (default about
      ``sqrt(n_steps)``; ``n_steps`` keeps every state).
    - `program`: ``"auto"`` (the engine decides); ``"array"`` or ``"scalar"`` (one forward
      layout whatever the batching, derivatives by JAX's ``jvp`` of the checkpointed array
      program: for benchmarks); ``"autodiff"`` (the checkpointed array program,
      differentiated and batched by JAX alone: the reference); ``"adjoint"`` (reverse mode
      always `so3jax._engine.derivatives.CheckpointedAdjoint`). On a JAX release outside
      `so3jax._engine._jax.TESTED` every program is ``"autodiff"``, with a warning.

    **Returns:** ``(observations, final carry)``; each observation leaf has a leading axis of
    ``n_steps // save_every`` (the states after steps ``save_every, 2 save_every, ...``).
    """
    if program not in _PROGRAMS:
        raise ValueError(f"program must be one of {_PROGRAMS}, got {program!r}")
    K = checkpoint_length(n_steps) if checkpoint is None else int(checkpoint)
    # closed-over tracers become explicit parameters, seen by derivatives and batching
    step_c, step_consts = jax.closure_convert(step, params, carry0)
    obs_c, obs_consts = jax.closure_convert(observe, params, carry0)
    P = (params, step_consts, obs_consts)

    def step_p(P, c):
        return step_c(P[0], c, *P[1])

    def obs_p(P, c):
        return obs_c(P[0], c, *P[2])

    loop = Programs(step_p, obs_p, n_steps, save_every, K)
    if program != "autodiff" and not _jax.supported():
        _jax.warn_reference_path()
        program = "autodiff"
    _plan.note("loop", n_steps=n_steps, save_every=save_every, program=program)
    if program == "autodiff":
        return loop.fwd_checkpointed(P, carry0)
    if program == "array":  # batched by `_dual` too, so every output is (`_batched_with`)
        fwd = _dual(loop.fwd_array, loop.fwd_array, "array")
    elif program == "scalar":
        fwd = _dual(scalarized.or_array(loop), partial(scalarized.forward, loop), "scalar")
    else:
        fwd = _dual(loop.fwd_array, partial(scalarized.forward, loop), "run")
    return derivatives.differentiated(loop, fwd, program)(P, carry0)
