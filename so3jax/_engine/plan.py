"""What the engine executes for a call, and why: `explain`.

The engine decides at trace time how a run executes (`so3jax._engine`): the layout of
each program (the array program, or the scalarized one for a large batch), whether it
runs in tiles or with fusion cuts, whether its loops compile as one kernel, and how it
is differentiated (the one-pass Jacobian, JAX's ``jvp`` of the checkpointed program, or
the discrete adjoint). Each decision point calls `note`; `explain` traces a function
(no compilation, no run) with a recorder installed and returns what was noted.

The recorder is a `contextvars.ContextVar`: nothing is recorded outside `explain`, and
nothing is shared between threads.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import functools
from collections.abc import Callable

import equinox as eqx
import jax

from . import policy

_RECORDER: contextvars.ContextVar[list | None] = contextvars.ContextVar("so3jax_plan", default=None)
#: `explain`'s own list: `traced` records there past any `deferred` block.
_ROOT: contextvars.ContextVar[list | None] = contextvars.ContextVar("so3jax_root", default=None)


def count() -> int:
    """How many decisions are recorded so far (0 outside `explain`)."""
    entries = _RECORDER.get()
    return 0 if entries is None else len(entries)


def noted_since(start: int, kind: str) -> bool:
    """Whether a decision of ``kind`` was recorded after the first ``start``."""
    entries = _RECORDER.get() or []
    return any(e["kind"] == kind for e in entries[start:])


@contextlib.contextmanager
def deferred():
    """Record the decisions taken inside into a list of their own (yielded; ``None``
    outside `explain`), for `extend` to keep or for the caller to drop: the trace of a
    program that a batch then replaces is not what runs."""
    if _RECORDER.get() is None:
        yield None
        return
    pending: list = []
    token = _RECORDER.set(pending)
    try:
        yield pending
    finally:
        _RECORDER.reset(token)


def extend(pending: list | None) -> None:
    """Keep decisions recorded by `deferred`."""
    entries = _RECORDER.get()
    if entries is not None and pending:
        entries.extend(pending)


def note(kind: str, **details) -> None:
    """Record one decision of the engine (a no-op outside `explain`)."""
    entries = _RECORDER.get()
    if entries is not None:
        entries.append({"kind": kind, **details})


def traced(fn: Callable, program: str) -> Callable:
    """``fn`` recording a ``"traced"`` entry each time it runs, that is each time JAX
    traces it, also inside a `deferred` block whose decisions are dropped: a trace costs
    its time whether its decisions are kept or not. Wrapping twice records once."""
    if getattr(fn, "_plan_program", None) == program:
        return fn

    @functools.wraps(fn)
    def call(*args, **kwargs):
        entries = _ROOT.get()
        if entries is not None:
            entries.append({"kind": "traced", "program": program})
        return fn(*args, **kwargs)

    call._plan_program = program
    return call


def jit(fn: Callable) -> Callable:
    """`equinox.filter_jit` of ``fn`` keyed by the engine's active policy
    (`so3jax._engine.policy.current`): a call under another policy traces again, and
    traces under that policy. Under `explain` ``fn`` is traced inline: a jitted function
    whose trace is cached would not take its decisions again."""

    def under(active, *args, **kwargs):
        with policy.using(active):
            return fn(*args, **kwargs)

    jitted = eqx.filter_jit(under)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if _RECORDER.get() is not None:
            return fn(*args, **kwargs)
        return jitted(policy.current(), *args, **kwargs)

    return call


@dataclasses.dataclass(frozen=True)
class Plan:
    """The engine's decisions for one call, in the order they were taken.

    **Fields:**

    - `entries`: a list of dicts, each with a ``"kind"``:
        - ``"loop"``: a fixed-step loop handed to the engine (``n_steps``,
          ``save_every``, ``program``: the caller's choice, ``"auto"`` by default);
        - ``"layout"``: how one program runs (``program``: ``"run"`` for the forward
          run, ``"jacobian"`` for the one-pass Jacobian, ``"adjoint"``, ``"jvp"`` for
          second derivatives; ``runs``: the batch it
          runs in, 1 for a single run; ``layout``: ``"array"`` or
          ``"scalarized"``; ``tiles``: ``(n, size)``; ``cuts``: fusion cuts on);
        - ``"derivative"``: how a run is differentiated (``strategy``:
          ``"one-pass Jacobian"``, ``"checkpointed jvp"`` (JAX's autodiff of the
          checkpointed array program), ``"checkpointed jvp, discrete adjoint"``
          or ``"second derivative"``; ``scalars``: the differentiated scalars; ``why``;
          for the one-pass Jacobian ``carried``: per float leaf of the loop's carry,
          whether the tangent program carries its tangent, ``False`` for a leaf no
          differentiated input reaches, such as the reference attitude under the
          gains); the strategies are `so3jax._engine.derivatives`' objects;
        - ``"adjoint"``: what the discrete adjoint's forward pass keeps for its backward
          pass (``saved``): ``"residuals"``, every step's (``bytes_per_step`` over
          ``steps``, within the policy's ``adjoint_residual_bytes``), or
          ``"checkpoints"``, the carries at the starts of ``segments`` of
          ``steps_per_segment`` steps, each replayed backward;
        - ``"traced"``: the array program of ``program`` traced by JAX (the engine traces
          each program once per call and batches that trace; every further entry is
          tracing time spent again);
        - ``"transpose"``: how a second derivative's tangent program is transposed
          (reverse over reverse): ``by="columns"``, the program run once per unit
          tangent through at most the policy's ``forward_jacobian_max`` ``scalars``,
          or ``by="array program"``, JAX's transpose of the array program;
        - ``"observations"``: what the one-pass Jacobian saves per observation leaf
          (``saved``, in the order of the leaves): ``"none"`` (no differentiated input
          reaches it: zeros outside the loop), ``"dense"`` (its full tangent), ``"right
          frame"`` or ``"left frame"`` (a rotation's tangent as three numbers, ``R
          hat(xi)`` or ``hat(xi) R``; the ``"frames"`` pass);
        - ``"tiles"``: a batch run in ``n`` tiles of ``size`` runs, one after the other;
        - ``"settle"``: a loop started where JAX's fixed point over its carry ends
          (``what``: ``"batched carry"`` with the ``components`` batched before the
          loop, or ``"carry tangents"`` with the ``leaves`` given zero tangents);
        - ``"frames"``: a scalarized Jacobian program carrying ``rotations`` attitude
          tangents as three numbers (0: every rotation's tangent as nine);
        - ``"hoisting"``: whether a loop compiles as one kernel on a CPU (``hoisted``,
          ``why`` when not).
    - `passes`: the optimisation passes the engine's policy runs (sorted names).
    """

    entries: list
    #: The optimisation passes the active policy runs (`so3jax._engine.policy.PASSES`).
    passes: tuple = ()

    def of(self, kind: str) -> list:
        """The entries of one kind."""
        return [e for e in self.entries if e["kind"] == kind]

    def __str__(self) -> str:
        if not self.entries:
            return "no fixed-step loop ran through the engine"
        lines = [f"passes: {', '.join(self.passes) or 'none (the reference path)'}"]
        for e in self.entries:
            details = ", ".join(f"{k}={v!r}" for k, v in e.items() if k != "kind")
            lines.append(f"{e['kind']}: {details}")
        return "\n".join(lines)


def explain(fn: Callable, *args, **kwargs) -> Plan:
    """What the engine will execute for ``fn(*args, **kwargs)``, and why.

    ``fn`` is traced, not compiled or run (as `jax.make_jaxpr` does); so3jax's own
    jitted entry points trace inline, so that every decision is taken again and
    recorded. Pass ``fn`` itself, not ``jax.jit(fn)``: a jitted function that has run
    before reuses its cached trace, and the plan would be empty. Use it to see why a
    call is slow: which layout a batch runs in, and how a gradient is taken.

    **Arguments:**

    - `fn`: a function that runs so3jax (e.g. ``jax.grad`` of a cost, ``jax.vmap``
      of `so3jax.simulate`).
    - `args`, `kwargs`: its arguments (arrays, or `jax.ShapeDtypeStruct`).

    **Returns:** a `Plan`; ``print(plan)`` lists the decisions.

    **Example:**

        plan = so3jax.explain(jax.grad(cost), gains)
        print(plan)   # derivative: strategy='one-pass Jacobian', scalars=2, ...
    """
    entries: list = []
    token, root = _RECORDER.set(entries), _ROOT.set(entries)
    try:
        jax.make_jaxpr(lambda *a: fn(*a, **kwargs))(*args)
    finally:
        _RECORDER.reset(token)
        _ROOT.reset(root)
    return Plan(entries, tuple(sorted(policy.current().passes)))
