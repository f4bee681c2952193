"""The ``"cuts"`` pass: fusion cuts where XLA on CPU would recompute shared values.

XLA on CPU fuses cheap producers into every consumer, so a value read by several
consumers is recomputed in each. A fusion cut (`fusion_cut`) is a boundary XLA does not
fuse across: the value is computed once. Program in, program out: `_eval_with_cuts`
evaluates a scalarized program's jaxpr with cuts placed where a value's cone reaches the
policy's ``cut_cone`` (``column_cut_cone`` for values that tangent columns consume);
`array_cut` / `derivative_cut` place them in the array programs' derivative rules.
A cut returns its operands unchanged, so results are bit-for-bit those without:
``tests/passes/test_cuts.py``. Speed: ``benchmarks/element_work.py``,
``benchmarks/ablation.py``.
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

    XLA on CPU fuses elementwise operations into their consumers and duplicates
    cheap producers into every consumer that needs them. In a scalarized step,
    where every carry component is its own fusion, that recomputes the shared
    part of the step once per output, a program many times the size of the step's.
    `optimization_barrier`
    does not stop it (the CPU compiler expands it into control dependencies
    before fusing); a `lax.switch` whose branches all return their operands is
    removed by JAX (outputs forwarded), and a two-way one with cheap branches
    becomes a `select` in XLA and is fused away. What is kept is a three-way
    switch whose first two branches are the identity and whose third (never
    taken) returns zeros: its results are buffers, so what follows reads them.

    ``index`` must be an unbatched int32 scalar, 0 or 1, whose value XLA
    cannot know at compile time (`cut_index`).
    """
    if not values:
        return values
    values = [jnp.asarray(v) for v in values]
    ident, never = _cut_branches(tuple(jax.typeof(v) for v in values))
    return cond_p.bind(index, *values, branches=(ident, ident, never))


def array_cut_index(tree):
    """An index for `fusion_cut`s in the array programs, computed from ``tree``; or ``None``.

    The array programs have the duplication `fusion_cut` describes too, where a
    derivative rule's primal matrices (``exp(w) - I`` and ``R (exp(w) - I)``,
    whose coefficients come from polynomials, not library calls) feed the
    products of a batch of tangent columns: XLA recomputes the matrices, sines
    and cosines included, in every element of each product. The rules cut them
    with an index computed from their own primal inputs (`cut_index`: unbatched
    under ``vmap``, unknown to XLA; through a ``stop_gradient``), so they need
    nothing from their caller and close over no outer tracer. ``None`` (no
    cuts) off CPU. The scalarizer drops these cuts (`_is_cut`): its programs
    place their own (`_eval_with_cuts`).
    """
    return cut_index(jax.lax.stop_gradient(tree))


def array_cut(index, *values) -> tuple:
    """``values``, through a `fusion_cut` at ``index`` unless it is ``None``."""
    return values if index is None else tuple(fusion_cut(list(values), index))


@jax.custom_jvp
def derivative_cut(*values) -> tuple:
    """``values`` unchanged; differentiated, the values and their tangents go through one
    `array_cut` (index from the values).

    For what a run's derivative programs recompute but its forward pass does not, or
    not enough to pay for a cut: a Runge-Kutta stage feeds every later stage. Cut there,
    a batch's Jacobian program runs faster, but a single run, where a conditional per
    stage costs more than the little work it saves, slower.
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

    What ``lax.switch(index, (ident, ident, never), values)`` would bind, without
    tracing three branches for every cut: tracing the seed's 4096-run forward
    program makes 49 cuts at 7 operand types, its B = 256 gradient 119 at 14;
    and JAX batches a branch it has batched before from its cache (the same
    jaxpr), so the cuts' branches are traced and batched that many times, not
    three per cut.
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
    # Unbatched under vmap (the batch axis is read as data): a batched index would
    # turn every cut into a `select`, which XLA fuses away.
    return _probe(xs), False


def _is_probe(params) -> bool:
    """Whether a ``custom_vmap_call``'s parameters are `cut_index`'s probe's."""
    return getattr(params["rule"], "rule", None) is _probe_rule


def cut_index(tree):
    """An int32 scalar, 0 or 1, computed from data in ``tree`` (see `fusion_cut`).

    It reads the first element of every floating-point leaf: any one of them
    may be a constant XLA folds (a scene or a batch of starts closed over by
    the caller's ``jit``), and a folded index would fold the cuts away with
    it. It stays unbatched under ``vmap``. ``None`` (no cuts) off CPU, where a
    conditional reads its index on the host, or when ``tree`` holds no
    floating-point data, or with the ``"cuts"`` pass off.
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

    A value with several consumers whose not-yet-materialized cone (the cheap
    operations XLA would recompute in each consumer) has at least ``cone_limit``
    operations goes through a `fusion_cut`. Expensive operations with several
    consumers XLA keeps by itself. Cuts wait until a consumer needs one, so
    that independent values share a cut.

    ``columns`` flags the inputs that a `vmap` around the program will batch (a
    Jacobian's tangent columns, `so3jax._engine.passes.scalarized.columns_outside`). XLA fuses an
    unbatched value's cone into each batched consumer and recomputes it for every
    column: the primal part of the seed's Jacobian step, recomputed in the columns'
    fusions, was a fifth of its work. So a value that a batched operation consumes is
    cut from a cone of the policy's ``column_cut_cone`` operations on.
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
