"""The ``"cuts"`` pass: fusion cuts where XLA on CPU would recompute shared values.

A fusion cut (`fusion_cut`) is a boundary XLA does not fuse across, so a value with several
consumers is computed once (docs/engine.md, "Fusion cuts"). Program in, program out:
`_eval_with_cuts` evaluates a scalarized program's jaxpr with cuts where a value's cone
reaches the policy's ``cut_cone`` (``column_cut_cone`` where tangent columns consume it);
`array_cut` / `derivative_cut` place them in the array programs' derivative rules. A cut
returns its operands unchanged, so results are bit-for-bit those without:
``tests/passes/test_pass_cuts.py``. Speed: ``benchmarks/ablation.py`` (``no cuts``),
``benchmarks/element_work.py``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap
from jax.extend import core as jex_core
from jax.extend.core.primitives import cond_p

from ..policy import current

__all__ = ["fusion_cut", "cut_index", "array_cut", "array_cut_index", "derivative_cut"]


def _is_cut(branches) -> bool:
    """Whether a ``cond``'s branches are a `fusion_cut`'s: the first two the identity."""
    if len(branches) != 3:
        return False
    return all(
        not b.jaxpr.eqns and b.jaxpr.outvars == b.jaxpr.invars and not b.consts
        for b in branches[:2]
    )


def fusion_cut(values: list, index) -> list:
    """``values`` unchanged, but computed once: a boundary XLA does not fuse across.

    A three-way switch whose first two branches are the identity and whose third (never
    taken) returns zeros; simpler barriers are removed by JAX or fused away by XLA
    (docs/engine.md, "Fusion cuts"). ``index``: an unbatched int32 scalar, 0 or 1, unknown
    to XLA at compile time (`cut_index`).
    """
    if not values:
        return values
    values = [jnp.asarray(v) for v in values]
    ident, never = _cut_branches(tuple(jax.typeof(v) for v in values))
    return cond_p.bind(index, *values, branches=(ident, ident, never))


def array_cut_index(tree):
    """An index for `fusion_cut`s in the array programs, computed from ``tree``; or ``None``.

    A derivative rule passes its own primal inputs (taken through ``stop_gradient``), so it
    needs nothing from its caller and closes over no outer tracer. ``None`` as `cut_index`.
    The scalarizer drops these cuts (`_is_cut`) and places its own (`_eval_with_cuts`).
    """
    return cut_index(jax.lax.stop_gradient(tree))


def array_cut(index, *values) -> tuple:
    """``values``, through a `fusion_cut` at ``index`` unless it is ``None``."""
    return values if index is None else tuple(fusion_cut(list(values), index))


@jax.custom_jvp
def derivative_cut(*values) -> tuple:
    """``values`` unchanged; differentiated, the values and their tangents go through one
    `array_cut` (index from the values).

    For what only the derivative programs recompute enough to pay for a cut (a Runge-Kutta
    stage read twice; docs/engine.md, "Fusion cuts").
    """
    return values


@derivative_cut.defjvp
def _derivative_cut_jvp(primals, tangents):
    n = len(primals)
    out = array_cut(array_cut_index(primals), *primals, *tangents)
    return tuple(out[:n]), tuple(out[n:])


@functools.lru_cache(maxsize=1024)
def _cut_branches(avals: tuple) -> tuple:
    """The branches of a `fusion_cut` at these operand types, traced once per process.

    What ``lax.switch(index, (ident, ident, never), values)`` would bind; one jaxpr per
    types also lets JAX reuse its batching of a branch (``tests/test_scalarize.py``,
    ``test_fusion_cut_branches_are_traced_once_per_operand_types``).
    """
    ident = jax.make_jaxpr(lambda *v: list(v))(*avals)
    never = jax.make_jaxpr(lambda *v: [jnp.zeros_like(x) for x in v])(*avals)
    assert not ident.consts and not never.consts
    return ident, never


@custom_vmap
def _probe(xs):
    total = functools.reduce(lambda a, b: a + b.astype(a.dtype), [jnp.ravel(x)[0] for x in xs])
    return jnp.isnan(total).astype(jnp.int32)


@_probe.def_vmap
def _probe_rule(axis_size, in_batched, xs):
    # Unbatched: a batched index would turn every cut into a `select` XLA fuses away.
    return _probe(xs), False


def _is_probe(params) -> bool:
    """Whether a ``custom_vmap_call``'s parameters are `cut_index`'s probe's."""
    return getattr(params["rule"], "rule", None) is _probe_rule


def cut_index(tree):
    """An int32 scalar, 0 or 1, computed from data in ``tree`` (see `fusion_cut`).

    It reads the first element of every floating-point leaf, since any one may be a
    constant XLA folds (and the cuts with it); unbatched under ``vmap``. ``None`` (no cuts)
    off CPU, without floating-point data in ``tree``, or with the ``"cuts"`` pass off.
    """
    if jax.default_backend() != "cpu" or not current().on("cuts"):
        return None
    xs = [
        x
        for x in jax.tree.leaves(tree)
        if jnp.size(x) and jnp.issubdtype(jnp.result_type(x), jnp.floating)
    ]
    return _probe(xs) if xs else None


def _bind(eqn, ins):
    out = eqn.primitive.bind(*ins, **eqn.primitive.get_bind_params(eqn.params))
    return out if eqn.primitive.multiple_results else [out]


#: Primitives XLA does not duplicate into several consumers (it keeps their result).
_EXPENSIVE = frozenset("div sqrt rsqrt cbrt sin cos tan exp exp2 expm1 log log1p atan2 pow".split())


def _eval_with_cuts(closed, args, index, cone_limit: int, columns=None):
    """Evaluate a jaxpr of scalar operations, cutting fusion where XLA would duplicate.

    A value with several consumers whose cone (the cheap, not yet materialized operations
    XLA would recompute in each) reaches ``cone_limit`` goes through a `fusion_cut` (XLA keeps
    an `_EXPENSIVE` one itself); values waiting for a cut share one. ``columns`` flags the
    inputs a `vmap` around the program batches (tangent columns, `scalarized.columns_outside`):
    a value a batched operation consumes is cut from the policy's ``column_cut_cone`` on.
    """
    jaxpr = closed.jaxpr
    col = dict.fromkeys(jaxpr.constvars, False)
    col.update(zip(jaxpr.invars, columns or [False] * len(args), strict=True))
    n_use, n_col = {}, {}
    for e in jaxpr.eqns:
        ins = [v for v in e.invars if isinstance(v, jex_core.Var)]
        batched = any(col[v] for v in ins)
        col.update(dict.fromkeys(e.outvars, batched))
        for v in ins:
            n_use[v] = n_use.get(v, 0) + 1
            if batched and not col[v]:
                n_col[v] = n_col.get(v, 0) + 1
    for v in jaxpr.outvars:
        if isinstance(v, jex_core.Var):
            n_use[v] = n_use.get(v, 0) + 1
    env = dict(zip(jaxpr.constvars, closed.consts, strict=True))
    env.update(zip(jaxpr.invars, args, strict=True))
    cone = {}  # ops XLA would recompute for each use of a var (0: materialized)

    def read(v):
        return v.val if isinstance(v, jex_core.Literal) else env[v]

    pending = {}  # vars waiting for a cut, in program order (a dict: deterministic HLO)

    def flush():
        live = list(pending)
        for v, x in zip(live, fusion_cut([env[v] for v in live], index), strict=True):
            env[v] = x
        pending.clear()

    for e in jaxpr.eqns:
        if any(isinstance(v, jex_core.Var) and v in pending for v in e.invars):
            flush()
        outs = _bind(e, [read(v) for v in e.invars])
        env.update(zip(e.outvars, outs, strict=True))
        c = 1 + sum(cone.get(v, 0) for v in e.invars if isinstance(v, jex_core.Var))
        for v in e.outvars:
            fan = n_use.get(v, 0)
            nc = n_col.get(v, 0)
            if (fan >= 2 or nc) and e.primitive.name in _EXPENSIVE:
                cone[v] = 0
            elif (fan >= 2 and c >= cone_limit) or (nc and c >= current().column_cut_cone):
                cone[v] = 0
                pending[v] = None
            else:
                cone[v] = c
    if pending:
        flush()
    return [read(v) for v in jaxpr.outvars]
