"""Tangent plumbing the derivative strategies share: JAX's ``jvp`` through flagged
leaves, linear maps with a custom transpose (so3jax's own ``linear_call``), and
first-order-only residuals. Nothing here registers anything with JAX.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from . import plan as _plan
from .linear_call import linear_call
from .policy import current, using
from .trees import (
    _batched_with,
    _fill,
    _front,
    _is_float,
    _pick,
    _spec,
    _tangent_leaves,
    _unit_columns,
)


def _float_tangent(fn: Callable, treedef, nz: list, out_nz: list) -> Callable:
    """``tangent(xs, ts, others, **kw)``: JAX's ``jvp`` of ``fn`` at the leaves ``others``,
    those flagged ``nz`` set to ``xs`` and moved by ``ts``; the output tangents flagged
    ``out_nz``. A ``batched`` keyword (flags of ``(xs, ts, others)``) reaches ``fn``
    as flags of its own arguments."""

    def tangent(xs, ts, others, **kw):
        if kw.get("batched") is not None:
            xb, _, ob = kw["batched"]
            kw["batched"] = tuple(jax.tree.unflatten(treedef, _fill(nz, xb, ob)))

        def g(*xs):
            return fn(*jax.tree.unflatten(treedef, _fill(nz, xs, others)), **kw)

        return _pick(out_nz, jax.tree.leaves(jax.jvp(g, tuple(xs), tuple(ts))[1]))

    return tangent


def _with_float0(out, out_nz: list, tan: list):
    """The tangent tree of ``out``: ``tan`` where ``out_nz``, ``float0`` zeros elsewhere."""
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

    ``fast`` (a `_dual`) runs as a ``linear_call``'s program; ``plain`` is the same map on
    the array program, and JAX's ``jvp`` of it is the derivative (docs/engine.md, "Second
    derivatives"). The transpose is ``fast`` once per unit tangent (`_transpose_by_columns`)
    through at most ``max_columns`` (default ``forward_jacobian_max``) scalars of the ``ts``
    flagged ``real`` (the others are zeros that only settle loops), else JAX's transpose
    of ``plain``. ``adjoint(res, cts)``, if given, is the transpose instead (``None`` for
    symbolic-zero cotangents; differentiated as ``plain``'s transpose); ``extra`` is what
    only it reads (``res[2]``), and ``out_shapes`` the tangent's shapes, so ``fast`` is
    traced (under the policy active here) only where the tangent is evaluated, not under
    ``grad``.
    """
    shapes = [_spec(t) for t in ts]
    n_real = sum(math.prod(s.shape) for s, r in zip(shapes, real, strict=True) if r)
    active = current()
    max_columns = active.forward_jacobian_max if max_columns is None else max_columns

    def callee(res, ts):
        with using(active):  # traced later with ``out_shapes``
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

    Gives a forward-mode-only program (a ``while_loop``) a reverse mode over its
    derivatives (``jacrev`` of ``jacfwd``). Integer outputs get ``float0`` tangents.
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
    """The transpose of ``linear`` (a linear map of arrays shaped ``shapes``) at ``cts``:
    one run of ``linear`` per unit input of the arrays flagged ``real`` (under
    `jax.lax.map`), contracted with ``cts``; zero cotangents for the others.
    Measured against JAX's transpose by `benchmarks/tune.py`'s Hessian rows.
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

    JAX batches a ``custom_jvp``'s function and rule apart; `_batched_with` and `_front`
    make them agree, so ``jax.hessian`` of a batch's mean cost concatenates like outputs.
    """
    leaves, treedef = jax.tree.flatten(primals)
    t_leaves, nz = _tangent_leaves(tangents)
    out, tan = _jvp_through(array_fn, treedef, leaves, t_leaves, nz)
    return _front(_batched_with(out, primals)), tan


def _jvp_through(fn: Callable, treedef, leaves: list, t_leaves: list, nz: list):
    """JAX's ``jvp`` of ``fn(*unflatten(leaves))`` through the leaves flagged ``nz`` alone
    (the others are constants: no tangent term where they are used)."""

    def g(*xs):
        return fn(*jax.tree.unflatten(treedef, _fill(nz, xs, leaves)))

    return jax.jvp(g, tuple(_pick(nz, leaves)), tuple(_pick(nz, t_leaves)))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def first_order_only(why: str, res):
    """``res`` (a ``linear_call``'s residuals) unchanged; ``NotImplementedError(why)`` if
    differentiated (JAX's own error there is a bare ``AssertionError``)."""
    return res


@first_order_only.defjvp
def _first_order_only_jvp(why, primals, tangents):
    raise NotImplementedError(why)
