"""The ``"hoist"`` pass: each loop of a program compiled as one kernel on a CPU.

Program in, program out: `_hoisted` takes a loop (a ``lax.scan`` and its arguments) and
returns its results from the same loop, traced once, staged as a jitted call that XLA's
older CPU emitter compiles whole (``xla_cpu_small_call``; docs/engine.md, "Loops as one
kernel"). Where it cannot, the loop runs as traced. Results equal the loop's to round-off:
``tests/passes/test_pass_hoist.py``. Speed: ``benchmarks/emitters.py``,
``benchmarks/ablation.py``.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import math
import warnings
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax.extend import core as jex_core

from .. import _jax, plan as _plan, policy as _policy
from ..policy import current, one_cpu_device
from . import scalarize as sc
from .unroll import _UNROLLED, _unrolled

#: What is being traced (`_tracing`): the runs in its batch (a vmapped program sees one
#: run's shapes), whether its loops may be hoisted, and whether loops with reductions may.
_TRACING: contextvars.ContextVar[tuple] = contextvars.ContextVar(
    "so3jax_tracing", default=(1, True, True)
)


@contextlib.contextmanager
def _tracing(what: str, runs: int = 1):
    """Trace program ``what`` (a `_dual`'s) in a batch of ``runs`` runs.

    Nothing is hoisted under a second derivative's ``"jvp"`` (`_dual_jvp`: it would compile
    much longer). Only forward runs hoist loops with reductions: a ``vmap`` around a staged
    derivative may batch them past ``hoist_max_reduced``
    (``tests/test_engine.py::test_vmap_of_grad_around_hoisted_loops_compiles``).
    """
    n, hoist, _ = _TRACING.get()
    token = _TRACING.set(
        (n * int(runs), hoist and what != "jvp", what in ("run", "scalar", "array"))
    )
    try:
        yield
    finally:
        _TRACING.reset(token)


#: Primitives a hoisted loop may hold: XLA's older CPU emitter refuses dots, convolutions,
#: scatters and custom calls. ``pad``, ``split`` and ``empty2`` are what JAX's transpose of a
#: step or loop adds (the discrete adjoint's loops).
_HOISTABLE = frozenset(
    """abs acos acosh add add_any and asin asinh atan atan2 atanh broadcast_in_dim cbrt ceil
    checkpoint clamp closed_call concatenate cond convert_element_type copy copy_p cos
    cosh custom_jvp_call custom_vjp_call custom_vjp_call_jaxpr custom_vmap_call div
    dynamic_slice dynamic_update_slice empty2 eq erf erf_inv erfc exp exp2 expm1 expand_dims floor
    ge gt integer_pow iota is_finite jit le log log1p logistic lt max min mul ne neg
    nextafter not optimization_barrier or pad pjit pow reduce_and reduce_max reduce_min
    reduce_or reduce_precision reduce_prod reduce_sum rem remat2 reshape rev round rsqrt scan
    select_n shift_left shift_right_arithmetic shift_right_logical sign sin sinh slice split
    sqrt square squeeze stack stop_gradient sub tan tanh transpose unstack while xor""".split()
)


def _hoistable(jaxpr, runs: int = 1, reductions: bool = True) -> bool:
    """Whether every equation of ``jaxpr`` (nested ones too) is in `_HOISTABLE`, with no
    reduction (none at all without ``reductions``) over more than ``hoist_max_reduced``
    elements in a batch of ``runs`` runs (``runs=0``: whatever its reductions)."""
    limit = current().hoist_max_reduced
    for e, _ in sc.equations(jaxpr):
        if e.primitive.name not in _HOISTABLE:
            return False
        if e.primitive.name in _UNROLLED and (
            not reductions or math.prod(e.invars[0].aval.shape) * runs > limit
        ):
            return False
    return True


def _largest_inner(jaxpr) -> int:
    """The bytes of the largest array made inside the bodies of ``jaxpr``'s loops and calls
    (at any depth), not ``jaxpr``'s own inputs and outputs."""
    return max(
        (
            math.prod(v.aval.shape) * v.aval.dtype.itemsize
            for e, depth in sc.equations(jaxpr)
            if depth > 0
            for v in e.outvars
            if hasattr(v.aval, "shape") and hasattr(v.aval, "dtype")
        ),
        default=0,
    )


@functools.cache
def warn_held_back() -> None:
    """Warn, once per process, that loops are not compiled as one kernel on this jaxlib."""
    warnings.warn(
        f"so3jax: this jaxlib is not one of {sorted(_jax.HOIST_TESTED)}, whose XLA compiles "
        "so3jax's loops as one kernel; they run as XLA builds them: the same results, several "
        "times slower on a CPU (benchmarks/ablation.py, 'no hoist'; SO3JAX_HOIST_LOOPS=1 "
        "forces it, at the risk of XLA aborting the process)",
        stacklevel=2,
    )


def _hoisted(loop: Callable, *args, xs_from: int | None = None):
    """``loop(*args)`` (a `lax.scan`), compiled as one kernel on a CPU where the policy and
    XLA's older emitter allow, with its reductions written out (`_unrolled`) if only they
    stand in the way; else run as traced. The plan notes the choice (``"hoisting"``).

    ``xs_from``: the index, among the leaves of ``args``, of the first one the loop scans
    over; ``hoist_max_bytes`` counts those by the slice one iteration reads.
    """
    runs, hoist, reductions = _TRACING.get()
    policy = current()
    if _jax.set_xla_metadata is None or not policy.on("hoist") or not hoist:
        why = "off (the policy's passes)" if hoist else "a second derivative's loop"
        if hoist and _policy.HOIST_HELD_BACK:
            why = "off: this jaxlib is not verified for it (_jax.HOIST_TESTED)"
            if one_cpu_device():
                warn_held_back()
        _plan.note("hoisting", hoisted=False, runs=runs, why=why)
        return loop(*args)
    # Several devices: XLA partitions after this choice and the older emitter cannot link the
    # collectives (tests/test_sweep.py::test_two_device_sharded_sweep_equals_single_device).
    if not one_cpu_device():
        _plan.note("hoisting", hoisted=False, runs=runs, why="not a single CPU device")
        return loop(*args)
    leaves = jax.tree.leaves(args)
    sizes = [jnp.size(x) * jnp.result_type(x).itemsize for x in leaves]
    if xs_from is not None:
        sizes = [
            b // max(1, jnp.shape(x)[0]) if i >= xs_from else b
            for i, (x, b) in enumerate(zip(leaves, sizes, strict=True))
        ]
    per_run = max(sizes, default=0)
    if per_run * runs > policy.hoist_max_bytes:
        _plan.note(
            "hoisting", hoisted=False, runs=runs, why="a leaf over the policy's hoist_max_bytes"
        )
        return loop(*args)
    closed, shape = jax.make_jaxpr(loop, return_shape=True)(*args)
    hoisted, why = closed, None
    if _largest_inner(closed.jaxpr) * runs >= policy.hoist_max_inner:
        why = "an array over the policy's hoist_max_inner"
    else:
        if not _hoistable(closed.jaxpr, runs, reductions) and _hoistable(closed.jaxpr, 0):
            hoisted = _unrolled(closed)  # only reductions stand in the way: write them out
        if not _hoistable(hoisted.jaxpr, runs, reductions):
            why = "a primitive or reduction XLA's older emitter refuses"
    if why is not None:  # run the traced loop, not again
        _plan.note("hoisting", hoisted=False, runs=runs, why=why)
        outs = jex_core.jaxpr_as_fun(closed)(*leaves)
        return jax.tree.unflatten(jax.tree.structure(shape), outs)
    _plan.note("hoisting", hoisted=True, runs=runs, unrolled=hoisted is not closed)
    # The barrier keeps XLA from sinking large constants into the call, on which the older
    # emitter aborts: tests/test_engine.py::test_hoisting_keeps_out_what_one_kernel_cannot_hold.
    consts, leaves = jax.lax.optimization_barrier((list(hoisted.consts), leaves))

    @jax.jit
    def call(consts, leaves):
        outs = jex_core.jaxpr_as_fun(jex_core.ClosedJaxpr(hoisted.jaxpr, consts))(*leaves)
        # Inputs kept live to the end, else the older emitter can abort on buffer reuse:
        # tests/test_engine.py::test_hoisted_call_returns_its_inputs.
        return outs, (consts, leaves)

    with _jax.set_xla_metadata(xla_cpu_small_call="true", inlineable="false"):
        outs, _ = call(consts, leaves)
    return jax.tree.unflatten(jax.tree.structure(shape), outs)
