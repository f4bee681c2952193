"""Tangent plumbing the derivative strategies share: JAX's ``jvp`` through flagged
leaves, linear maps with a custom transpose, and first-order-only residuals.

`_linear_tangent` wraps a tangent program (linear in its tangents) as so3jax's own
``linear_call`` primitive (`so3jax._engine.linear_call`), whose transpose runs the
program once per unit tangent (`_transpose_by_columns`) or JAX's transpose of the plain
array program. `forward_differentiated` gives a forward-mode-only program (a
``while_loop``) a reverse mode that way. Nothing here registers anything with JAX.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from . import linear_call as _linear_call, plan as _plan
from .linear_call import linear_call
from .policy import current, using
from .trees import (
    _batched_with,
    _fill,
    _front,
    _is_float,
    _pick,
    _tangent_leaves,
    _unit_columns,
)


def _float_tangent(fn: Callable, treedef, nz: list, out_nz: list) -> Callable:
    """``tangent(xs, ts, others, **kw)``: JAX's ``jvp`` of ``fn`` at the leaves
    ``others`` (``treedef``'s) with those flagged in ``nz`` set to ``xs`` and moved by
    ``ts``; the tangents of its outputs flagged in ``out_nz`` (the float ones). A
    ``batched`` keyword (a `custom_vmap` rule's flags of ``(xs, ts, others)``) reaches
    ``fn`` as its own arguments' flags."""

    def tangent(xs, ts, others, **kw):
        if kw.get("batched") is not None:
            xb, _, ob = kw["batched"]
            kw["batched"] = tuple(jax.tree.unflatten(treedef, _fill(nz, xb, ob)))

        def g(*xs):
            return fn(*jax.tree.unflatten(treedef, _fill(nz, xs, others)), **kw)

        return _pick(out_nz, jax.tree.leaves(jax.jvp(g, tuple(xs), tuple(ts))[1]))

    return tangent


def _with_float0(out, out_nz: list, tan: list):
    """The tangent tree of ``out``: ``tan`` for the leaves flagged in ``out_nz``, ``float0``
    zeros for the others (integer and boolean outputs)."""
    leaves = jax.tree.leaves(out)
    zeros = [
        None if k else np.zeros(jnp.shape(o), jax.dtypes.float0)
        for o, k in zip(leaves, out_nz, strict=True)
    ]
    return jax.tree.unflatten(jax.tree.structure(out), _fill(out_nz, tan, zeros))


def _linear_tangent(
    plain: Callable,
    fast: Callable,
    xs,
    others,
    ts,
    real: list,
    max_columns=None,
    adjoint=None,
    extra=None,
    out_shapes=None,
):
    """``fast(xs, ts, others)``, linear in ``ts``, transposable and differentiable.

    ``fast`` (a `_dual`: a ``custom_vmap`` that JAX can neither partially evaluate nor
    transpose) runs as the program of a ``linear_call``. Its transpose (``grad`` of
    ``grad``): through at most the policy's ``forward_jacobian_max`` scalars of the ``ts`` flagged
    ``real`` (the others are zeros that only settle loops), ``fast`` once per unit
    tangent, contracted with the cotangent (`_transpose_by_columns`); through more,
    JAX's transpose of ``plain`` (the same map on the array program). Behind a
    ``custom_jvp`` whose rule is JAX's ``jvp`` of ``plain``, because a ``linear_call``
    cannot differentiate its residuals: third derivatives. ``max_columns``: the
    largest number of columns (default the policy's ``forward_jacobian_max``);
    `forward_differentiated` takes columns whatever their number. ``adjoint(res, cts)``,
    if given, is the transpose whatever the number of scalars, with ``None`` for each
    cotangent that is a symbolic zero (`linear_call`'s ``symbolic_zeros``); a second
    derivative through it (reverse over reverse) differentiates JAX's transpose of
    ``plain`` instead (`linear_call`'s ``differentiable``). ``extra``: residuals only
    ``adjoint`` reads, as ``res[2]`` (the map does not depend on them). ``out_shapes``
    (with ``adjoint``): the tangent's shapes, so that ``fast`` is traced only where the
    tangent is evaluated (forward mode), not under ``grad`` (`linear_call`'s
    ``out_shapes``), under the policy active here.
    """
    shapes = [jax.ShapeDtypeStruct(jnp.shape(t), jnp.result_type(t)) for t in ts]
    n_real = sum(math.prod(s.shape) for s, r in zip(shapes, real, strict=True) if r)
    active = current()
    max_columns = active.forward_jacobian_max if max_columns is None else max_columns

    def callee(res, ts):
        with using(active):  # (traced later with ``out_shapes``)
            return fast(res[0], ts, res[1])

    def transpose(res, cts):
        if 0 < n_real <= max_columns:
            _plan.note("transpose", by="columns", scalars=n_real)
            return _transpose_by_columns(lambda ts: callee(res, ts), cts, shapes, real)
        _plan.note("transpose", by="array program", scalars=n_real)
        zeros = [jnp.zeros(s.shape, s.dtype) for s in shapes]
        return jax.vjp(lambda ts: plain(res[0], ts, res[1]), zeros)[1](cts)[0]

    def differentiable(res, ts):  # what a second derivative of ``adjoint`` differentiates
        return plain(res[0], ts, res[1])

    @jax.custom_jvp
    def tangent(xs, others, ts, extra):
        if adjoint is not None:
            return linear_call(
                callee,
                adjoint,
                (xs, others, extra),
                ts,
                symbolic_zeros=True,
                differentiable=differentiable,
                out_shapes=out_shapes,
            )
        return linear_call(callee, transpose, (xs, others), ts)

    def tangent_jvp(primals, tangents):
        return _array_jvp(lambda xs, others, ts, _: plain(xs, ts, others), primals, tangents)

    tangent.defjvp(tangent_jvp, symbolic_zeros=True)
    return tangent(xs, others, ts, extra)


def forward_differentiated(fn: Callable) -> Callable:
    """``fn`` with JAX's ``jvp`` of it as its derivative, behind a ``linear_call`` whose
    transpose runs that ``jvp`` once per unit tangent (`_transpose_by_columns`).

    For programs JAX differentiates in forward mode only (a ``while_loop``: an adaptive
    run through `diffrax.ForwardMode`, whose one-pass Jacobian is such a program): reverse
    mode over their derivatives (``jacrev`` of ``jacfwd``, ``grad`` of a gradient's norm)
    then works, instead of raising JAX's "Reverse-mode differentiation does not work for
    lax.while_loop". Integer outputs get ``float0`` tangents.
    """

    @jax.custom_jvp
    def call(*args):
        return fn(*args)

    def rule(primals, tangents):
        leaves, treedef = jax.tree.flatten(primals)
        t_leaves, nonzero = _tangent_leaves(tangents)
        nz = [z and _is_float(x) for x, z in zip(leaves, nonzero, strict=True)]
        out = call(*primals)
        out_nz = [_is_float(o) for o in jax.tree.leaves(out)]
        plain = _float_tangent(fn, treedef, nz, out_nz)
        xs, ts = _pick(nz, leaves), _pick(nz, t_leaves)
        tan = _linear_tangent(plain, plain, xs, leaves, ts, [True] * len(ts), math.inf)
        return out, _with_float0(out, out_nz, tan)

    call.defjvp(rule, symbolic_zeros=True)
    return call


def _transpose_by_columns(linear: Callable, cts, shapes: list, real: list) -> list:
    """The transpose of ``linear`` (a linear map of arrays shaped as ``shapes``) at
    ``cts``, from one run of ``linear`` per unit input of the arrays flagged ``real``
    (under `jax.lax.map`: one program for all columns), each contracted with ``cts``.
    The arrays not flagged get zero cotangents: only zeros ever enter there.

    Reverse over reverse through a few gains (``jax.jacrev(jax.jacrev(cost))``) runs
    this way several times faster, and compiles faster, than JAX's transpose of the
    array program (`benchmarks/tune.py`'s Hessian rows).
    """
    zeros = [jnp.zeros(s.shape, s.dtype) for s in shapes]
    cols = _unit_columns(_pick(real, zeros))

    def column(col):
        out = linear(_fill(real, list(col), zeros))
        pairs = zip(jax.tree.leaves(cts), jax.tree.leaves(out), strict=True)
        terms = [jnp.sum(c * o) for c, o in pairs]
        return functools.reduce(jnp.add, terms)

    vals = jax.lax.map(column, cols)
    picked = _pick(real, shapes)
    parts = jnp.split(vals, np.cumsum([math.prod(s.shape) for s in picked])[:-1].tolist())
    cotangents = [p.reshape(s.shape).astype(s.dtype) for p, s in zip(parts, picked, strict=True)]
    return _fill(real, cotangents, zeros)


def _array_jvp(array_fn: Callable, primals, tangents):
    """JAX's ``jvp`` of ``array_fn`` through the nonzero tangents, its outputs batched as
    `_dual`'s batching rule batches them: every output, batch axis first.

    JAX batches a ``custom_jvp`` call's function and its rule apart, and a jitted
    batch (``vmap`` of `so3jax.rollout_cost`, say) fixes each output's batch axis
    from the function's. `_dual`'s ``custom_vmap`` batches every output on axis 0;
    JAX's ``vmap`` of a ``scan`` stacks on axis 0 and batches on axis 1, and leaves
    unbatched what no batched input moves. `_batched_with` and `_front` make the two
    agree, so that ``jax.hessian`` of the mean cost over a batch of starts
    concatenates outputs batched alike.
    """
    leaves, treedef = jax.tree.flatten(primals)
    t_leaves, nz = _tangent_leaves(tangents)
    out, tan = _jvp_through(array_fn, treedef, leaves, t_leaves, nz)
    return _front(_batched_with(out, primals)), tan


def _jvp_through(fn: Callable, treedef, leaves: list, t_leaves: list, nz: list):
    """JAX's ``jvp`` of ``fn(*unflatten(leaves))`` through the leaves flagged in ``nz``
    alone (the others enter as constants: no tangent term where they are used)."""

    def g(*xs):
        return fn(*jax.tree.unflatten(treedef, _fill(nz, xs, leaves)))

    return jax.jvp(g, tuple(_pick(nz, leaves)), tuple(_pick(nz, t_leaves)))


def _linear_call_batches() -> bool:
    """Whether so3jax's own batching ``linear_call`` primitive (`so3jax._engine.linear_call`) is
    available; where it is not, the engine runs its reference programs and says so once."""
    if not _linear_call.AVAILABLE:  # pragma: no cover - a JAX release that moved the tables
        warnings.warn(
            "so3jax: this JAX release lacks the rule tables so3jax's linear_call primitive "
            "needs (jax.interpreters.ad / batching / mlir); derivatives run as JAX's "
            "autodiff of the array program (slower: the one-pass Jacobian and the discrete "
            "adjoint are off)",
            stacklevel=2,
        )
    return _linear_call.AVAILABLE


_HAVE_LINEAR_CALL_BATCHING = _linear_call_batches()


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def first_order_only(why: str, res):
    """``res`` (residuals of a ``linear_call``) unchanged; ``NotImplementedError(why)``
    if they are differentiated, as in a second derivative: ``linear_call`` cannot
    differentiate its residuals, and the error says why (JAX's is a bare
    ``AssertionError``)."""
    return res


@first_order_only.defjvp
def _first_order_only_jvp(why, primals, tangents):
    raise NotImplementedError(why)
