"""Scalarization: run a small-array function as a program over scalar components.

A step of an attitude integrator works on dozens of 3-vectors and 3x3 matrices.
XLA on CPU turns such code into a hundred or more separate kernels per step
(every reduction, `stack` and shape change ends a fusion), and each kernel
launch costs about 50–100 ns, far more than its arithmetic. Under `vmap` the
batch axis goes in front of every small array, so the same kernels then also
stride through memory (an array-of-structures layout).

`scalarize` rewrites the function instead: it traces it once to a jaxpr at
the given shapes and evaluates that jaxpr with every array replaced by a
NumPy *object* array of its scalar components (each a JAX scalar, or a
``(B,)`` array under `vmap`). Shape operations (`reshape`, `slice`,
`broadcast_in_dim`, `concatenate`, `transpose`, ...) only rearrange
components and emit nothing; elementwise operations apply per component;
`dot_general` and reductions unroll into sums. What is left is one flat
elementwise program over scalars, which XLA fuses into a few kernels; under
`vmap` each component becomes a contiguous ``(B,)`` array: a structure-of-arrays
layout with no transposes. The result is the same function (the same
primitives, in the same order of operations per component), and it stays
differentiable (it is made of JAX operations).

Only the primitives a vector field or a step needs are supported (elementwise
arithmetic and transcendental functions, comparisons and `select_n`, shape
operations, `dot_general`, sums/max/min reductions, nested `jit`, custom
JVP/VJP calls and `cond`); anything else (loops, dynamic indexing, sorting)
raises `NotImplementedError`, and callers fall back to the plain function.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap
from jax.extend import core as jex_core
from jax.extend.core.primitives import cond_p

from . import _jax

__all__ = [
    "scalarize",
    "flat_program",
    "fusion_cut",
    "cut_index",
    "split",
    "join",
    "to_components",
    "from_components",
    "ScalarizeError",
]


class ScalarizeError(NotImplementedError):
    """A primitive the scalarizing interpreter does not handle."""


_ELEMENTWISE = frozenset(
    """
    abs acos acosh add add_any and asin asinh atan atan2 atanh cbrt ceil clamp convert_element_type
    copy copy_p cos cosh div eq erf erf_inv erfc exp exp2 expm1 floor ge gt imag integer_pow
    is_finite le lgamma digamma log log1p logistic lt max min mul ne neg nextafter not or pow
    real reduce_precision rem round rsqrt select_n sign sin sinh sqrt square sub tan tanh xor
    stop_gradient
    """.split()
)


def _obj(shape) -> np.ndarray:
    return np.empty(shape, dtype=object)


def to_components(x) -> np.ndarray:
    """An array of shape ``S`` as an object array of shape ``S`` of JAX scalars."""
    x = jnp.asarray(x)
    out = _obj(x.shape)
    for idx in np.ndindex(*x.shape):
        out[idx] = x[idx]
    return out


def from_components(c: np.ndarray, batch_shape=()) -> jax.Array:
    """Stack an object array of components (each of ``batch_shape``) into one array."""
    flat = [jnp.broadcast_to(v, batch_shape) for v in c.reshape(-1)]
    if not flat:
        raise ValueError("empty component array")
    return jnp.stack(flat, axis=-1).reshape(tuple(batch_shape) + c.shape)


def _const(value, aval=None) -> np.ndarray:
    """A literal or constant as components.

    Concrete values become NumPy scalars, which `_elementwise` can fold at trace
    time (multiplications by exact zeros and ones from `eye`, `hat`, ...);
    traced values (closed over from an outer trace) stay JAX scalars.
    """
    if isinstance(value, jax.core.Tracer):
        arr = value
        conv = lambda v: v
    else:
        arr = np.asarray(value)
        dtype = aval.dtype if aval is not None else arr.dtype
        conv = lambda v: np.asarray(v, dtype=dtype)[()]
    out = _obj(np.shape(arr))
    for idx in np.ndindex(*np.shape(arr)):
        out[idx] = conv(arr[idx])
    return out


def _cast(dtype):
    return lambda x: np.asarray(x).astype(dtype)[()]


_FOLDABLE = {
    "eq": lambda a, b: np.equal(a, b)[()],
    "ne": lambda a, b: np.not_equal(a, b)[()],
    "lt": lambda a, b: np.less(a, b)[()],
    "le": lambda a, b: np.less_equal(a, b)[()],
    "gt": lambda a, b: np.greater(a, b)[()],
    "ge": lambda a, b: np.greater_equal(a, b)[()],
    "and": lambda a, b: np.logical_and(a, b)[()] if a.dtype == bool else np.bitwise_and(a, b)[()],
    "or": lambda a, b: np.logical_or(a, b)[()] if a.dtype == bool else np.bitwise_or(a, b)[()],
    "not": lambda a: np.logical_not(a)[()] if a.dtype == bool else np.invert(a)[()],
    "neg": lambda a: np.negative(a)[()],
    "add": lambda a, b: np.add(a, b)[()],
    "sub": lambda a, b: np.subtract(a, b)[()],
    "mul": lambda a, b: np.multiply(a, b)[()],
    "max": lambda a, b: np.maximum(a, b)[()],
    "min": lambda a, b: np.minimum(a, b)[()],
}


def _is_const(x) -> bool:
    return isinstance(x, (np.generic, np.ndarray))


def _fold(name, xs, params):
    """Trace-time simplification when some operands are NumPy constants, or None."""
    consts = [_is_const(x) for x in xs]
    if not any(consts):
        return None
    if all(consts) and name in _FOLDABLE:
        return _FOLDABLE[name](*xs)
    if name == "mul":
        a, b = xs
        for c, other in ((a, b), (b, a)):
            if _is_const(c) and not _is_const(other):
                if c == 0:  # x * 0 -> 0 (drops NaN propagation through exact zeros)
                    return np.zeros((), dtype=c.dtype)[()]
                if c == 1:
                    return other
    elif name == "add":
        a, b = xs
        if _is_const(a) and not _is_const(b) and a == 0:
            return b
        if _is_const(b) and not _is_const(a) and b == 0:
            return a
    elif name == "sub":
        a, b = xs
        if _is_const(b) and not _is_const(a) and b == 0:
            return a
        if _is_const(a) and not _is_const(b) and a == 0:
            return -b
    elif name == "convert_element_type" and consts[0]:
        return _cast(params["new_dtype"])(xs[0])
    elif name == "select_n" and consts[0]:
        return xs[1 + int(xs[0])]
    return None


def _bshape(vals):
    return jnp.broadcast_shapes(*(jnp.shape(v) for v in vals))


def _elementwise(prim, params, args):
    """Apply ``prim`` per component (NumPy broadcasting over the component arrays)."""

    name = prim.name

    def one(*xs):
        folded = _fold(name, xs, params)
        if folded is not None:
            return folded
        shape = _bshape(xs)
        xs = [jnp.broadcast_to(x, shape) for x in xs]
        return prim.bind(*xs, **params)

    if prim.multiple_results:  # pragma: no cover - no such elementwise primitive here
        raise ScalarizeError(prim.name)
    return np.frompyfunc(one, len(args), 1)(*args)


def _sum(vals):
    vals = list(vals)
    out = vals[0]
    for v in vals[1:]:
        out = out + v
    return out


def _reduce(x: np.ndarray, axes, combine, identity: Callable) -> np.ndarray:
    """``combine`` over ``axes``; over an empty axis, the NumPy constant ``identity()``."""
    axes = tuple(sorted(axes))
    keep = [d for d in range(x.ndim) if d not in axes]
    xt = x.transpose(keep + list(axes))
    out_shape = tuple(x.shape[d] for d in keep)
    xt = xt.reshape(out_shape + (-1,))
    out = _obj(out_shape)
    for idx in np.ndindex(*out_shape):
        parts = list(xt[idx])
        out[idx] = functools.reduce(combine, parts) if parts else identity()
    return out


def _dot_general(lhs, rhs, dimension_numbers, **_):
    (lc, rc), (lb, rb) = dimension_numbers
    lf = [d for d in range(lhs.ndim) if d not in lc and d not in lb]
    rf = [d for d in range(rhs.ndim) if d not in rc and d not in rb]
    L = lhs.transpose(list(lb) + lf + list(lc))
    Rr = rhs.transpose(list(rb) + rf + list(rc))
    bshape = tuple(lhs.shape[d] for d in lb)
    lfs = tuple(lhs.shape[d] for d in lf)
    rfs = tuple(rhs.shape[d] for d in rf)
    nc = int(np.prod([lhs.shape[d] for d in lc], dtype=int))
    L = L.reshape(bshape + lfs + (nc,))
    Rr = Rr.reshape(bshape + rfs + (nc,))
    out = _obj(bshape + lfs + rfs)
    for b in np.ndindex(*bshape):
        for i in np.ndindex(*lfs):
            for j in np.ndindex(*rfs):
                lv, rv = L[b + i], Rr[b + j]
                if nc == 0:
                    raise ScalarizeError("dot_general with an empty contraction")
                out[b + i + j] = _sum(lv[k] * rv[k] for k in range(nc))
    return out


def _pad(x, padding_value, padding_config):
    pv = padding_value[()]
    for lo, hi, _ in padding_config:
        if lo < 0 or hi < 0:
            raise ScalarizeError("pad with negative padding")
    shape = tuple(
        lo + hi + n + max(n - 1, 0) * interior
        for n, (lo, hi, interior) in zip(x.shape, padding_config, strict=True)
    )
    out = _obj(shape)
    out[...] = pv
    idx = tuple(
        slice(lo, lo + n + max(n - 1, 0) * interior, interior + 1)
        for n, (lo, hi, interior) in zip(x.shape, padding_config, strict=True)
    )
    out[idx] = x
    return out


def _iota(dtype, shape, dimension, **_):
    out = _obj(shape)
    for idx in np.ndindex(*shape):
        out[idx] = np.asarray(idx[dimension], dtype=dtype)[()]
    return out


def _select_branches(index, results_per_branch):
    """Elementwise choice among branch results (every branch was evaluated)."""
    outs = []
    for parts in zip(*results_per_branch, strict=True):
        sel = lambda i, *xs: jax.lax.select_n(
            jnp.broadcast_to(i, _bshape((i,) + xs)),
            *[jnp.broadcast_to(x, _bshape((i,) + xs)) for x in xs],
        )
        outs.append(np.frompyfunc(sel, len(parts) + 1, 1)(index, *parts))
    return outs


def _eval(jaxpr, consts, args):
    env = {}

    def read(v):
        if isinstance(v, jex_core.Literal):
            return _const(v.val, v.aval)
        return env[v]

    for v, c in zip(jaxpr.constvars, consts, strict=True):
        env[v] = c
    for v, a in zip(jaxpr.invars, args, strict=True):
        env[v] = a
    for eqn in jaxpr.eqns:
        ins = [read(v) for v in eqn.invars]
        outs = _apply(eqn, ins)
        if not eqn.primitive.multiple_results:
            outs = [outs]
        for v, o in zip(eqn.outvars, outs, strict=True):
            if not isinstance(o, np.ndarray):  # a 0-d result of np.frompyfunc
                arr = _obj(())
                arr[()] = o
                o = arr
            env[v] = o
    return [read(v) for v in jaxpr.outvars]


def _closed(cj, args):
    return _eval(cj.jaxpr, [_const(c) for c in cj.consts], args)


def _lowest(dtype):
    if dtype == np.bool_:
        return False
    return -np.inf if np.issubdtype(dtype, np.floating) else np.iinfo(dtype).min


def _highest(dtype):
    if dtype == np.bool_:
        return True
    return np.inf if np.issubdtype(dtype, np.floating) else np.iinfo(dtype).max


#: Reductions: how two components combine, and the result over an empty axis.
_REDUCTIONS = {
    "reduce_sum": (lambda a, b: a + b, lambda dt: 0),
    "reduce_prod": (lambda a, b: a * b, lambda dt: 1),
    "reduce_max": (jnp.maximum, _lowest),
    "reduce_min": (jnp.minimum, _highest),
    "reduce_and": (jnp.logical_and, lambda dt: True),
    "reduce_or": (jnp.logical_or, lambda dt: False),
}


def _apply(eqn, ins):
    name = eqn.primitive.name
    p = eqn.params
    if name in _ELEMENTWISE:
        return _elementwise(eqn.primitive, p, ins)
    x = ins[0] if ins else None
    if name == "broadcast_in_dim":
        shape, dims = p["shape"], p["broadcast_dimensions"]
        expanded = [1] * len(shape)
        for src, dst in enumerate(dims):
            expanded[dst] = x.shape[src]
        return np.broadcast_to(x.reshape(expanded), shape)
    if name == "reshape":
        return x.reshape(p["new_sizes"])
    if name in ("reshard", "sharding_constraint"):
        # A layout annotation (e.g. `zeros_like` of a sharded array): components carry none.
        return x
    if name == "squeeze":
        return x.reshape(tuple(n for d, n in enumerate(x.shape) if d not in p["dimensions"]))
    if name == "expand_dims":
        return np.expand_dims(x, p["dimensions"])
    if name == "transpose":
        return x.transpose(p["permutation"])
    if name == "rev":
        return np.flip(x, p["dimensions"])
    if name == "slice":
        strides = p["strides"] or (1,) * x.ndim
        idx = tuple(
            slice(s, e, st)
            for s, e, st in zip(p["start_indices"], p["limit_indices"], strides, strict=True)
        )
        return x[idx]
    if name == "concatenate":
        return np.concatenate(ins, axis=p["dimension"])
    if name == "stack":
        return np.stack(ins, axis=p["axis"])
    if name == "unstack":
        return [np.take(x, i, axis=p["axis"]) for i in range(x.shape[p["axis"]])]
    if name == "split":
        cuts = np.cumsum(p["sizes"])[:-1]
        return list(np.split(x, cuts, axis=p["axis"]))
    if name == "pad":
        return _pad(x, ins[1], p["padding_config"])
    if name == "iota":
        return _iota(**p)
    if name == "dot_general":
        return _dot_general(ins[0], ins[1], p["dimension_numbers"])
    if name in _REDUCTIONS:
        combine, identity = _REDUCTIONS[name]
        dtype = eqn.outvars[0].aval.dtype
        return _reduce(x, p["axes"], combine, lambda: np.asarray(identity(dtype), dtype)[()])
    if name in ("pjit", "jit", "closed_call", "core_call", "remat", "remat2", "checkpoint"):
        cj = p.get("jaxpr") or p.get("call_jaxpr")
        if isinstance(cj, jex_core.ClosedJaxpr):
            return _closed(cj, ins)
        return _eval(cj, [], ins)
    if name == "custom_jvp_call":
        return _closed(p["call_jaxpr"], ins)
    if name == "custom_vjp_call":
        cj = p.get("call_jaxpr") or p.get("fun_jaxpr")
        return _closed(cj, ins)
    if name == "custom_vmap_call":
        if _is_probe(p):
            # `cut_index`'s probe, whose only consumers are the cuts dropped below:
            # evaluated, it would add a consumer to the values it reads, and
            # `_eval_with_cuts` would cut them (B = 256 gradient: 1.15x slower).
            return [_const(np.int32(0))]
        return _closed(p["call"], ins)
    if name == "cond":
        index, ops = ins[0], ins[1:]
        if _is_cut(p["branches"]):  # an array program's `fusion_cut`: cut anew here
            return list(ops)
        results = [_closed(br, ops) for br in p["branches"]]
        if len(results) == 1:
            return results[0]
        return _select_branches(index, results)
    raise ScalarizeError(f"scalarize: primitive {name!r} is not supported")


_STRUCTURAL = frozenset(
    """
    broadcast_in_dim reshape squeeze expand_dims transpose rev slice concatenate stack unstack
    split pad iota dot_general reduce_sum reduce_max reduce_min reduce_and reduce_or
    reduce_prod pjit jit closed_call core_call remat remat2 checkpoint custom_jvp_call
    custom_vjp_call custom_vmap_call cond reshard sharding_constraint
    """.split()
)


def _is_cut(branches) -> bool:
    """Whether a ``cond``'s branches are a `fusion_cut`'s: the first two the identity."""
    if len(branches) != 3:
        return False
    return all(
        not b.jaxpr.eqns and b.jaxpr.outvars == b.jaxpr.invars and not b.consts
        for b in branches[:2]
    )


def subjaxprs(params: dict) -> list:
    """The jaxprs in an equation's ``params`` (a loop's body, a conditional's branches)."""
    out = []
    for v in params.values():
        for sub in v if isinstance(v, (tuple, list)) else (v,):
            if isinstance(sub, jex_core.ClosedJaxpr):
                out.append(sub.jaxpr)
            elif isinstance(sub, jex_core.Jaxpr):
                out.append(sub)
    return out


def _check(jaxpr) -> None:
    """Raise `ScalarizeError` up front for any primitive `_apply` does not handle."""
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name not in _ELEMENTWISE and name not in _STRUCTURAL:
            raise ScalarizeError(f"scalarize: primitive {name!r} is not supported")
        for sub in subjaxprs(eqn.params):
            _check(sub)


def scalarize(fn: Callable, *example_args) -> Callable:
    """``fn`` as a function over component arrays.

    Traces ``fn(*example_args)`` (pytrees of arrays, single-trajectory shapes)
    once, and returns ``run(*component_args)`` taking and returning the same
    pytrees with every leaf an object array of components (`to_components`).
    """
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*example_args)
    _check(closed.jaxpr)
    consts = [_const(c) for c in closed.consts]
    in_tree = jax.tree.structure(example_args)
    out_tree = jax.tree.structure(out_shape)

    def run(*component_args):
        leaves = in_tree.flatten_up_to(component_args)
        outs = _eval(closed.jaxpr, consts, leaves)
        return jax.tree.unflatten(out_tree, outs)

    return run


def _flat_components(tree) -> list:
    """Every scalar component of every leaf of ``tree``, in order."""
    return [leaf[idx] for leaf in jax.tree.leaves(tree) for idx in np.ndindex(*jnp.shape(leaf))]


def _parts(flat, shapes) -> list:
    """Split a flat list of components into object arrays of the given shapes."""
    out, i = [], 0
    for sh in shapes:
        n = int(np.prod(sh, dtype=int))
        a = _obj(n)
        for k in range(n):
            a[k] = flat[i + k]
        out.append(a.reshape(sh))
        i += n
    return out


#: A value with several consumers is cut (`fusion_cut`) when XLA would recompute at
#: least this many operations for each of them (`flat_program`). Measured on the
#: seed batches: 6 to 10 run alike; 3 or 12 and more are slower for some methods.
CUT_CONE = 8
#: A value that tangent columns batched around the program consume (`_eval_with_cuts`'s
#: ``columns``) is cut from this cone on. Counted on the seed's gradient over 256 runs
#: (tiles of 64, two columns) as element operations a step (XLA's instructions weighted
#: by the elements their fusion computes, `benchmarks/element_work.py`), a cone of 4
#: does less work than no column cuts for RKMK4, CF4, CG3 and LieEuler; 2 about the
#: same as 4, 6 to 32 more work than none.
COLUMN_CUT_CONE = 4


def fusion_cut(values: list, index) -> list:
    """``values`` unchanged, but computed once: a boundary XLA does not fuse across.

    XLA on CPU fuses elementwise operations into their consumers and duplicates
    cheap producers into every consumer that needs them. In a scalarized step,
    where every carry component is its own fusion, that recomputes the shared
    part of the step once per output: the seed's RKMK4 step (about 2300 scalar
    operations) compiled to about 25000, ten times over. `optimization_barrier`
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
    not enough to pay for a cut: a Runge-Kutta stage feeds every later stage, and
    cutting there made the Jacobian program of RKMK4 in Cayley coordinates over 16
    seed runs 1.5x faster, but a single run of the quadrotor (4000 steps) 1.36x slower,
    a conditional per stage costing about 0.3 us where a run does little work.
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
    floating-point data.
    """
    if jax.default_backend() != "cpu":
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
    Jacobian's tangent columns, `so3jax._engine._columns_outside`). XLA fuses an
    unbatched value's cone into each batched consumer and recomputes it for every
    column: the primal part of the seed's Jacobian step, recomputed in the columns'
    fusions, was a fifth of its work. So a value that a batched operation consumes is
    cut from a cone of `COLUMN_CUT_CONE` operations on.
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
            elif (fan >= 2 and c >= cone_limit) or (nc and c >= COLUMN_CUT_CONE):
                cone[v] = 0
                pending[v] = None
            else:
                cone[v] = c
    if pending:
        flush()
    return [read(v) for v in jaxpr.outvars]


def flat_program(fn: Callable, example, index=None, cut_cone: int = CUT_CONE, columns=None):
    """``fn`` (one pytree in, one out) as a function of flat scalar component lists.

    Returns ``(run, out_struct)``: ``run(flat)`` takes the components of a pytree
    shaped like ``example`` (as `split` gives them) and returns the list of the
    components of ``fn``'s output, each cast to its leaf's dtype;
    ``out_struct`` is ``jax.eval_shape(fn, example)``. Raises `ScalarizeError`
    when ``fn`` uses a primitive the interpreter does not handle.

    With an ``index`` from `cut_index` (see `fusion_cut`), the scalar program
    is cut wherever XLA would otherwise recompute ``cut_cone`` or more
    operations once per consumer of a value: the fused computations of the
    batched seed step drop from about 25000 HLO instructions to about 6500 (the
    program has 2300 scalar operations), and it runs 1.4 to 2.4x faster.
    """
    run = scalarize(fn, example)
    leaves, tree = jax.tree.flatten(example)
    shapes = [jnp.shape(leaf) for leaf in leaves]
    out_struct = jax.eval_shape(fn, example)
    out_dtypes = [(s.shape, s.dtype) for s in jax.tree.leaves(out_struct)]

    def plain(flat):
        out = run(jax.tree.unflatten(tree, _parts(flat, shapes)))
        out_leaves = jax.tree.leaves(out)
        return [
            jnp.asarray(v, dtype=dt)
            for leaf, (_, dt) in zip(out_leaves, out_dtypes, strict=True)
            for v in np.asarray(leaf, dtype=object).reshape(-1)
        ]

    if index is None:
        return plain, out_struct

    jaxprs = {}

    def closed_for(flat):
        """The jaxpr of the uncut flat program at these components' types (traced once)."""
        key = tuple((jnp.shape(v), jnp.result_type(v)) for v in flat)
        if key not in jaxprs:
            jaxprs[key] = jax.make_jaxpr(plain)([jax.ShapeDtypeStruct(*k) for k in key])
        return jaxprs[key]

    def run_flat(flat):
        flat = [jnp.asarray(v) for v in flat]
        return _eval_with_cuts(closed_for(flat), flat, index, cut_cone, columns)

    run_flat.closed_for = closed_for
    return run_flat, out_struct


def _batched_const(x) -> bool:
    """Whether a constant of a flat program is batched by an enclosing `vmap`
    (`so3jax._jax.batched`)."""
    return _jax.batched(x)


def batched_components(run_flat, flat: list, batched: list, dtypes=None) -> list | None:
    """Which carry components a loop of ``run_flat`` batches, given those batched at the start.

    The fixed point of "depends on a batched value" over the flat program's jaxpr
    (``run_flat`` maps the carry's components to the next carry's, same layout).
    ``None`` without ``run_flat.closed_for`` (a program without fusion cuts).
    With ``dtypes``, the program is taken at scalar components of those types
    (``flat`` may then hold arrays: columns of tangents run by a `vmap` of it).
    """
    closed_for = getattr(run_flat, "closed_for", None)
    if closed_for is None:
        return None
    if dtypes is not None:
        flat = [jax.ShapeDtypeStruct((), dt) for dt in dtypes]
    closed = closed_for(flat)
    const_b = [_batched_const(c) for c in closed.consts]
    return carry_fixed_point(closed.jaxpr, list(batched), 0, len(batched), const_b)


#: Primitives that call a jaxpr once with their operands, walked inside by the flag
#: walks here and in `_engine` (loops and conditionals have rules of their own).
CALL_PRIMITIVES = frozenset(
    "pjit jit closed_call core_call custom_jvp_call custom_vjp_call remat checkpoint".split()
)


def batched_outputs(jaxpr, flags: list, const_flags=()) -> list:
    """Which outputs of ``jaxpr`` a ``vmap`` batches, given which inputs (and constvars,
    ``const_flags``; unbatched if not given) are batched. Never fewer than JAX batches."""
    consts = const_flags or [False] * len(jaxpr.constvars)
    env = dict(zip(jaxpr.constvars, consts, strict=True))
    env.update(zip(jaxpr.invars, flags, strict=True))

    def read(v):
        return isinstance(v, jex_core.Var) and env.get(v, False)

    for e in jaxpr.eqns:
        env.update(zip(e.outvars, eqn_batched(e, [read(v) for v in e.invars]), strict=True))
    return [read(v) for v in jaxpr.outvars]


def scan_split(e) -> tuple[int, int] | None:
    """How many of scan equation ``e``'s operands are constants and how many the carry.

    JAX up to 0.10 names both counts in the equation's parameters; 0.11 describes the
    operands as three groups instead (``ft_in``: constants, carry, per-iteration
    inputs). ``None`` where neither reading fits the body (a later JAX): callers then
    leave the batching of that loop to JAX.
    """
    prm = e.params
    body = prm["jaxpr"].jaxpr
    if "num_consts" in prm:
        return prm["num_consts"], prm["num_carry"]
    try:
        consts, carry, _ = prm["ft_in"].unpack()
        nc, ncar = len(consts), len(carry)
    except (KeyError, AttributeError, TypeError, ValueError):
        return None

    def types(vs):
        return [(v.aval.shape, v.aval.dtype) for v in vs]

    fits = len(body.invars) == len(e.invars) and len(body.outvars) == len(e.outvars)
    if not fits or types(body.invars[nc : nc + ncar]) != types(body.outvars[:ncar]):
        return None
    return nc, ncar


def carry_fixed_point(body, flags: list, num_consts: int, num_carry: int, const_flags=()):
    """The batched flags of a loop's carry at the fixed point of its ``body`` (a jaxpr
    taking consts, carry and per-iteration inputs, returning the carry first), as
    JAX's ``scan`` finds it by batching the body until nothing changes."""
    carry = list(flags[num_consts : num_consts + num_carry])
    while True:
        ins = flags[:num_consts] + carry + flags[num_consts + num_carry :]
        out = batched_outputs(body, ins, const_flags)[:num_carry]
        new = [a or b for a, b in zip(carry, out, strict=True)]
        if new == carry:
            return carry
        carry = new


def eqn_batched(e, flags: list) -> list:
    """Which outputs of equation ``e`` a ``vmap`` batches (never fewer than JAX does)."""
    n = len(e.outvars)
    if not any(flags):
        return [False] * n
    name, prm = e.primitive.name, e.params
    if name == "custom_vmap_call" and _is_probe(prm):
        return [False] * n  # `cut_index`'s probe stays unbatched
    if name == "scan" and (split := scan_split(e)) is not None:
        nc, ncar = split
        body = prm["jaxpr"].jaxpr
        carry = carry_fixed_point(body, flags, nc, ncar)
        ys = batched_outputs(body, flags[:nc] + carry + flags[nc + ncar :])[ncar:]
        return carry + ys
    if name == "cond" and not flags[0]:
        branches = [batched_outputs(b.jaxpr, flags[1:]) for b in prm["branches"]]
        return [any(f) for f in zip(*branches, strict=True)]
    inner = prm.get("jaxpr", prm.get("call_jaxpr"))
    inner = getattr(inner, "jaxpr", inner)
    if (
        name in CALL_PRIMITIVES
        and isinstance(inner, jex_core.Jaxpr)
        and len(inner.invars) == len(flags)
    ):
        return batched_outputs(inner, flags)
    return [True] * n


def settle_batched(run_flat, flat: list, batched: list, one, dtypes=None) -> list:
    """``flat`` with the carry components that a loop of ``run_flat`` batches batched now.

    Under `vmap`, a `lax.scan` whose carry starts partly unbatched finds by
    itself which components become batched after a step, by batching its body
    again until nothing changes: each round re-traces the whole scalarized step
    (about 3000 equations for the seed's RKMK4), and nested scans multiply the
    rounds (three for the seed's forward loop). `batched_components` finds the
    same fixed point on the flat program's jaxpr, and those components are
    batched up front (``x + one`` with ``one`` a batched zero), so that each
    scan batches its body once. Components that stay unbatched (a reference
    attitude shared by the batch) stay so.

    ``batched[i]`` says whether ``flat[i]`` is batched already; ``dtypes`` as in
    `batched_components`. Without fusion cuts (no ``run_flat.closed_for``)
    ``flat`` is returned unchanged.
    """
    flags = batched_components(run_flat, flat, batched, dtypes)
    if flags is None:
        return flat

    def batch(x):
        x = jnp.asarray(x)
        if x.dtype == jnp.bool_:
            return jnp.logical_or(x, one != 0)
        return x + one.astype(x.dtype)

    return [batch(x) if f and not f0 else x for x, f, f0 in zip(flat, flags, batched, strict=True)]


def split(tree) -> list:
    """The flat list of scalar components of every leaf of ``tree``."""
    return _flat_components(tree)


def join(flat, struct, lead: tuple = ()):
    """Rebuild a pytree shaped like ``struct`` from components with leading shape ``lead``.

    ``flat`` lists the components in `split` order; each has shape ``lead`` (for
    example the saved points of a scan over components).
    """
    out, i = [], 0
    leaves, tree = jax.tree.flatten(struct)
    for s in leaves:
        n = int(np.prod(s.shape, dtype=int))
        if n == 0:
            out.append(jnp.zeros(tuple(lead) + tuple(s.shape), s.dtype))
            continue
        comps = [jnp.broadcast_to(jnp.asarray(v, s.dtype), lead) for v in flat[i : i + n]]
        out.append(jnp.stack(comps, axis=-1).reshape(tuple(lead) + tuple(s.shape)))
        i += n
    return jax.tree.unflatten(tree, out)
