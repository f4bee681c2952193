"""What the engine executes for a call, and why: `explain`.

Each trace-time decision of the engine calls `note`; `explain` traces a function with a
recorder installed (a `contextvars.ContextVar`: nothing recorded outside `explain`, nothing
shared between threads) and returns what was noted.
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
    """Record the decisions inside into a list of their own (yielded; ``None`` outside
    `explain`), for `extend` to keep or the caller to drop (a trace a batch replaces)."""
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
    """``fn`` recording a ``"traced"`` entry each time JAX traces it, even inside a
    dropped `deferred` block. Wrapping twice records once."""
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
    """`equinox.filter_jit` of ``fn`` keyed by the active policy (`policy.current`): a
    call under another policy traces again, under it. Traced inline under `explain`, so
    its decisions are taken again."""

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
        - ``"loop"``: a fixed-step loop (``n_steps``, ``save_every``, ``program``, ``"auto"``
          by default).
        - ``"layout"``: how ``program`` (``"run"``, ``"jacobian"``, ``"adjoint"``, ``"jvp"``)
          runs a batch of ``runs``: ``layout`` (``"array"``, ``"scalarized"``), ``cuts``, ``why``.
        - ``"derivative"``: a run's ``strategy`` (``"one-pass Jacobian"``, ``"checkpointed jvp"``,
          ``"checkpointed jvp, discrete adjoint"``, ``"second derivative"``;
          `so3jax._engine.derivatives`), ``scalars``, ``why``; for the one-pass Jacobian,
          ``carried``: per float carry leaf, whether its tangent is carried.
        - ``"adjoint"``: what the discrete adjoint keeps: ``saved="residuals"`` (``bytes_per_step``,
          ``steps``) or ``"checkpoints"`` (``segments``, ``steps_per_segment``).
        - ``"traced"``: JAX traced ``program``; each further entry for it is tracing spent again.
        - ``"transpose"``: a second derivative's transpose, ``by="columns"`` (at most
          ``forward_jacobian_max`` ``scalars``) or ``"array program"``.
        - ``"observations"``: what the one-pass Jacobian saves per observation leaf (``saved``):
          ``"none"``, ``"dense"``, ``"right frame"`` (``R hat(xi)``) or ``"left frame"``.
        - ``"tiles"``: ``program``'s batch of ``runs`` run as ``n`` tiles of ``size``.
        - ``"settle"``: a loop started at JAX's fixed point over its carry (``what``:
          ``"batched carry"`` with ``components``, or ``"carry tangents"`` with ``leaves``).
        - ``"frames"``: ``rotations`` whose tangents a scalarized Jacobian carries as 3 numbers.
        - ``"hoisting"``: whether a loop is one CPU kernel (``hoisted``, ``runs``; else ``why``).
    - `passes`: the passes the active policy runs (sorted names).
    """

    entries: list
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

    ``fn`` is traced, not compiled or run. Pass ``fn`` itself, not ``jax.jit(fn)``: a
    jitted function reuses its cached trace, and the plan would be empty.

    **Arguments:**

    - `fn`: a function that runs so3jax (e.g. ``jax.grad`` of a cost).
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
