"""The execution engine: how every fixed-step run executes.

`simulate`, `rollout_cost` / `expected_cost`, `sweep` and `tune` step a carry with a
pure step function and observe it every ``save_every`` steps. They hand that loop to
`run`; `explain` says what a call executes and why.

How to read it, smallest first:

- `so3jax._engine.loop`: the reference programs, a plain ``lax.scan`` and its
  checkpointed segments. With ``program="autodiff"`` that is all a run is.
- `so3jax._engine.derivatives`: the derivative strategies as objects (`Autodiff`, the
  reference; `OnePassJacobian`; `CheckpointedAdjoint`, the discrete adjoint) and `choose`,
  which picks one.
- `so3jax._engine.layout`: one run executes the array program; a batch under ``vmap``
  the scalarized one from the policy's threshold on (a ``custom_vmap`` rule, so nested
  ``vmap`` and ``vmap`` inside ``jit`` take it).
- `so3jax._engine.policy`: every threshold and switch, in one frozen `Policy`.
- `so3jax._engine.passes`: the optimisations, one module each (scalarize, cuts, frames,
  hoist, unroll, tiles), each proving its equality with the reference in
  ``tests/passes/`` and measured by ``benchmarks/ablation.py``.
- `so3jax._engine.programs`: the derivative programs the strategies build (the Jacobian
  and adjoint programs of one loop); their scalarized layout is the pass's
  (`so3jax._engine.passes.scalarized`).
- `so3jax._engine._jax`: every JAX internal touched, behind a version gate: on a JAX
  release outside it, every run takes the reference path and warns once.

The design and its measurements: ``docs/engine.md`` and ``docs/performance.md``.
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

    - `step`: ``step(params, carry) -> carry``, one step (pure; a carry may
      hold integer leaves such as a step counter and a status code).
    - `observe`: ``observe(params, carry) -> pytree`` of float arrays.
    - `params`: a pytree of arrays the loop depends on; its float leaves (and
      those of ``carry0``) are what derivatives flow to.
    - `n_steps`, `save_every`: Python ints, ``n_steps % save_every == 0``.
    - `checkpoint`: steps per checkpointed segment of the adjoint (default
      about ``sqrt(n_steps)``; ``n_steps`` keeps every state).
    - `program`: ``"auto"`` (the engine decides, see the module docstring);
      ``"array"`` or ``"scalar"`` (one layout for the forward run whatever the
      batching, derivatives from JAX's ``jvp`` of the checkpointed array
      program: for benchmarks); ``"autodiff"`` (the checkpointed array
      program, differentiated and batched by JAX alone: the reference);
      ``"adjoint"`` (reverse mode always the engine's discrete adjoint,
      `so3jax._engine.derivatives.CheckpointedAdjoint`; layouts per the policy).

    **Returns:** ``(observations, final carry)``; every observation leaf has a
    leading axis of length ``n_steps // save_every`` (the states after steps
    ``save_every, 2 save_every, ...``).
    """
    if program not in _PROGRAMS:
        raise ValueError(f"program must be one of {_PROGRAMS}, got {program!r}")
    K = checkpoint_length(n_steps) if checkpoint is None else int(checkpoint)
    # Closed-over tracers (a reference that closes over a traced amplitude, say)
    # become explicit parameters, so derivatives and batching see them.
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
