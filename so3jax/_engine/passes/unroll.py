"""The ``"unroll"`` pass: small reductions written out term by term.

Program in, program out: `_unrolled` returns a ``ClosedJaxpr`` with every reduction over at
most ``unroll_max_terms`` terms written as a chain of binary operations in row-major order, so
that a hoisted loop (`hoist`) holds none whatever a later ``vmap`` gives it (docs/engine.md,
"Reductions written out"). Values equal to round-off: ``tests/passes/test_pass_unroll.py``.
Speed: ``benchmarks/ablation.py`` (``run grad``).
"""

from __future__ import annotations

import itertools
import math
import weakref

import jax
from jax.extend import core as jex_core

from ..policy import current
from . import scalarize as sc

#: The reductions of `_HOISTABLE`, with the binary operation `_unrolled` chains them by.
_UNROLLED = {
    "reduce_sum": jax.lax.add,
    "reduce_prod": jax.lax.mul,
    "reduce_max": jax.lax.max,
    "reduce_min": jax.lax.min,
    "reduce_and": jax.lax.bitwise_and,
    "reduce_or": jax.lax.bitwise_or,
}


def _small_reduction(e) -> bool:
    if e.primitive.name not in _UNROLLED:
        return False
    shape = e.invars[0].aval.shape
    return (
        0 < math.prod(shape)
        and math.prod(shape[a] for a in e.params["axes"]) <= current().unroll_max_terms
    )


#: What `_has_small_reduction` and `_unrolled` found for a jaxpr (by identity, while it lives).
_SMALL_MEMO: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


_UNROLLED_MEMO: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _has_small_reduction(jaxpr) -> bool:
    found = _SMALL_MEMO.get(jaxpr)
    if found is None:
        found = _SMALL_MEMO[jaxpr] = any(
            _small_reduction(e) or any(_has_small_reduction(j) for j in sc.subjaxprs(e.params))
            for e in jaxpr.eqns
        )
    return found


def _unrolled(closed):
    """``closed`` (a `ClosedJaxpr`) with its reductions over at most ``unroll_max_terms``
    terms, nested jaxprs' too, written out term by term (`_eval_unrolled`); ``closed``
    itself with the pass off or nothing to write out."""
    if not current().on("unroll") or not _has_small_reduction(closed.jaxpr):
        return closed
    out = _UNROLLED_MEMO.get(closed)
    if out is None:
        args = [
            jax.ShapeDtypeStruct(v.aval.shape, v.aval.dtype, weak_type=v.aval.weak_type)
            for v in closed.jaxpr.invars
        ]
        out = jax.make_jaxpr(lambda *a: _eval_unrolled(closed.jaxpr, closed.consts, a))(*args)
        _UNROLLED_MEMO[closed] = out
    return out


def _unrolled_param(v):
    """An equation's parameter with the jaxprs in it `_unrolled`."""
    if type(v) in (tuple, list):  # (not a named tuple of numbers)
        return type(v)(_unrolled_param(x) for x in v)
    if isinstance(v, jex_core.ClosedJaxpr):
        return _unrolled(v)
    if isinstance(v, jex_core.Jaxpr) and not v.constvars and _has_small_reduction(v):
        out = _UNROLLED_MEMO.get(v)
        if out is None:  # () for "keep v": the memo must not hold its own key
            closed = _unrolled(jex_core.ClosedJaxpr(v, ()))
            out = _UNROLLED_MEMO[v] = () if closed.consts else (closed.jaxpr,)
        return out[0] if out else v
    return v


#: Elementwise primitives through which `_eval_unrolled` takes a reduction's term back to
#: their operands.
_TERMWISE = frozenset(
    """abs add add_any atan2 convert_element_type cos cosh div exp expm1 integer_pow
    log log1p max min mul neg rsqrt select_n sign sin sinh sqrt square sub tan tanh""".split()
)


def _eval_unrolled(jaxpr, consts, args) -> list:
    """Evaluate ``jaxpr`` with its small reductions written out term by term.

    A term is taken back through its producer where only the reduction reads it and the
    producer is elementwise (`_TERMWISE`) or a broadcast, else sliced:
    ``sum(A[:, :, None] * B[None], 1)`` becomes ``A[:, 0, None] * B[None, 0] + ...``.
    """
    env = dict(zip(jaxpr.constvars, consts, strict=True))
    env.update(zip(jaxpr.invars, args, strict=True))
    producer, uses, terms = {}, {}, {}
    for e in jaxpr.eqns:
        for v in e.invars:
            if isinstance(v, jex_core.Var):
                uses[v] = uses.get(v, 0) + 1
        producer.update(dict.fromkeys(e.outvars, e))
    for v in jaxpr.outvars:
        if isinstance(v, jex_core.Var):
            uses[v] = uses.get(v, 0) + 1

    def read(v):
        return v.val if isinstance(v, jex_core.Literal) else env[v]

    def term(v, at: tuple):
        """``v`` at index ``i`` of each of its axes ``a``, for ``(a, i)`` in ``at``."""
        if (v, at) not in terms:
            terms[v, at] = _term(v, at)
        return terms[v, at]

    def _term(v, at):
        shape, gone = v.aval.shape, {a for a, _ in at}
        left = tuple(n for d, n in enumerate(shape) if d not in gone)
        e = producer.get(v)
        if e is not None and uses[v] == 1 and len(e.outvars) == 1:
            if e.primitive.name in _TERMWISE:
                ins = [
                    term(u, tuple((a, i if u.aval.shape[a] != 1 else 0) for a, i in at))
                    if isinstance(u, jex_core.Var) and u.aval.ndim == len(shape)
                    else read(u)
                    for u in e.invars
                ]
                with e.ctx.manager:
                    return e.primitive.bind(*ins, **e.params)
            if e.primitive.name == "broadcast_in_dim":
                (u,) = e.invars
                dims = e.params["broadcast_dimensions"]
                index = dict(at)
                u_at = tuple(
                    (j, index[d] if u.aval.shape[j] != 1 else 0)
                    for j, d in enumerate(dims)
                    if d in index
                )
                kept = [d for j, d in enumerate(dims) if d not in index]
                u_val = term(u, u_at) if u_at else read(u)
                new_dims = tuple(d - sum(a < d for a in gone) for d in kept)
                with e.ctx.manager:
                    return jax.lax.broadcast_in_dim(u_val, left, new_dims)
        start, limit = [0] * len(shape), list(shape)
        for a, i in at:
            start[a], limit[a] = i, i + 1
        return jax.lax.reshape(jax.lax.slice(read(v), start, limit), left)

    for e in jaxpr.eqns:
        with e.ctx.manager:
            if _small_reduction(e) and isinstance(e.invars[0], jex_core.Var):
                (x,) = e.invars
                axes = sorted(e.params["axes"])
                outs = None
                for idx in itertools.product(*(range(x.aval.shape[a]) for a in axes)):
                    t = term(x, tuple(zip(axes, idx, strict=True)))
                    outs = t if outs is None else _UNROLLED[e.primitive.name](outs, t)
                outs = [outs]
            else:
                ins = [read(v) for v in e.invars]
                params = {k: _unrolled_param(v) for k, v in e.params.items()}
                outs = e.primitive.bind(*ins, **e.primitive.get_bind_params(params))
                outs = outs if e.primitive.multiple_results else [outs]
        env.update(zip(e.outvars, outs, strict=True))
    return [read(v) for v in jaxpr.outvars]
