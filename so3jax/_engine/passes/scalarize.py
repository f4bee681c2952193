"""Scalarization: run a small-array function as a program over scalar components.

Program in, program out: `scalarize` traces a function once and evaluates its jaxpr with
every array a NumPy *object* array of scalar components (JAX scalars, ``(B,)`` arrays under
`vmap`): one flat elementwise program, the same primitives in the same order per component,
still differentiable (docs/engine.md, "Scalarization"). A primitive outside `_ELEMENTWISE`
and `_STRUCTURAL` raises `ScalarizeError`, and callers run the plain function.

Equal to the array program to round-off: ``tests/passes/test_pass_scalarize.py``,
``tests/test_scalarize.py``. Speed: ``benchmarks/ablation.py`` (``no scalarize``),
``benchmarks/layouts.py``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jex_core

from .. import _jax
from ..policy import current
from ..trees import _batch_by
from .cuts import _eval_with_cuts, _is_cut, _is_probe

__all__ = [
    "scalarize",
    "flat_program",
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
    stop_gradient shift_left shift_right_logical shift_right_arithmetic
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
    """A literal or constant as components: NumPy scalars if concrete (folded by `_fold`),
    JAX scalars if traced (closed over from an outer trace)."""
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


#: Constants with more elements than this stay whole (`_Table`).
TABLE_MIN = 64


class _Table:
    """A large constant (a table: a `so3jax.Gust`'s path) kept whole.

    ``lax.dynamic_slice`` reads it whole (`_read_table`: one gather, no component added);
    any other use takes its components (`_const`), once."""

    def __init__(self, value):
        self.value = value
        self._components = None

    def components(self) -> np.ndarray:
        if self._components is None:
            self._components = _const(self.value)
        return self._components


def is_table(x) -> bool:
    """Whether a constant is kept whole (`_Table`): more than `TABLE_MIN` elements."""
    return jnp.ndim(x) >= 1 and jnp.size(x) > TABLE_MIN


def _materialized(x):
    return x.components() if isinstance(x, _Table) else x


def _read_table(table: _Table, starts: list, slice_sizes) -> np.ndarray:
    """``lax.dynamic_slice`` of a whole table at component starts, as components."""
    starts = [jnp.asarray(_index_value(i)) for i in starts]
    return to_components(jax.lax.dynamic_slice(jnp.asarray(table.value), starts, slice_sizes))


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


def _index_value(i: np.ndarray):
    """A 0-d component array of an index as one value (a NumPy or a JAX scalar)."""
    return i[()] if isinstance(i, np.ndarray) else i


def _dynamic_slice(x: np.ndarray, starts: list, slice_sizes) -> np.ndarray:
    """`lax.dynamic_slice` over components: constant starts slice, computed ones gather.

    Starts clamp as in `lax.dynamic_slice`. A computed start reads the stacked components
    by `_take` (one gather per output component); along an axis longer than the policy's
    ``scalarize_table_max`` it raises `ScalarizeError`.
    """
    out = x
    for axis, (start, size) in enumerate(zip(starts, slice_sizes, strict=True)):
        n = out.shape[axis]
        s = _index_value(start)
        if _is_const(s):
            lo = int(np.clip(int(s), 0, n - size))
            out = np.take(out, range(lo, lo + size), axis=axis)
            continue
        if n > current().scalarize_table_max:
            raise ScalarizeError(
                f"scalarize: dynamic_slice of a table of {n} entries (the policy's "
                f"scalarize_table_max is {current().scalarize_table_max})"
            )
        s = jnp.clip(jnp.asarray(s), 0, n - size)
        moved = np.moveaxis(out, axis, 0)
        res = _obj((size,) + moved.shape[1:])
        for idx in np.ndindex(*moved.shape[1:]):
            parts = [jnp.asarray(v) for v in moved[(slice(None),) + idx]]
            shape = _bshape(parts)
            table = jnp.stack([jnp.broadcast_to(v, shape) for v in parts])
            for m in range(size):
                res[(m,) + idx] = _take(table, s + m)
        out = np.moveaxis(res, 0, axis)
    return out


def _take(table, i):
    """``table[i]`` along the first axis: ``i`` a scalar, or one index per run (the
    trailing batch shape of ``table``)."""
    if jnp.ndim(i) == 0:
        return jax.lax.dynamic_index_in_dim(table, i, 0, keepdims=False)
    shape = jnp.broadcast_shapes(table.shape[1:], jnp.shape(i))
    table = jnp.broadcast_to(table, table.shape[:1] + shape)
    i = jnp.broadcast_to(i, shape)
    return jnp.take_along_axis(table, i[None], axis=0)[0]


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
        if any(isinstance(x, _Table) for x in ins):
            if eqn.primitive.name == "dynamic_slice" and isinstance(ins[0], _Table):
                env[eqn.outvars[0]] = _read_table(ins[0], ins[1:], eqn.params["slice_sizes"])
                continue
            if eqn.primitive.name not in _CALLS:
                ins = [_materialized(x) for x in ins]
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


def _broadcast_in_dim(x, p):
    expanded = [1] * len(p["shape"])
    for src, dst in enumerate(p["broadcast_dimensions"]):
        expanded[dst] = x.shape[src]
    return np.broadcast_to(x.reshape(expanded), p["shape"])


def _slice(x, p):
    strides = p["strides"] or (1,) * x.ndim
    starts, limits = p["start_indices"], p["limit_indices"]
    return x[tuple(slice(*b) for b in zip(starts, limits, strides, strict=True))]


#: Shape operations on NumPy arrays of any dtype (components here, element masks in
#: `so3jax._engine.masks`): ``(operands, params) -> [outputs]``. They move entries only.
SHAPE_OPS = {
    "broadcast_in_dim": lambda xs, p: [_broadcast_in_dim(xs[0], p)],
    "reshape": lambda xs, p: [xs[0].reshape(p["new_sizes"])],
    "squeeze": lambda xs, p: [np.squeeze(xs[0], axis=tuple(p["dimensions"]))],
    "expand_dims": lambda xs, p: [np.expand_dims(xs[0], p["dimensions"])],
    "transpose": lambda xs, p: [xs[0].transpose(p["permutation"])],
    "rev": lambda xs, p: [np.flip(xs[0], p["dimensions"])],
    "slice": lambda xs, p: [_slice(xs[0], p)],
    "concatenate": lambda xs, p: [np.concatenate(xs, axis=p["dimension"])],
    "stack": lambda xs, p: [np.stack(xs, axis=p["axis"])],
    "unstack": lambda xs, p: [
        np.take(xs[0], i, axis=p["axis"]) for i in range(xs[0].shape[p["axis"]])
    ],
    "split": lambda xs, p: np.split(xs[0], np.cumsum(p["sizes"])[:-1], axis=p["axis"]),
}


def _apply(eqn, ins):
    name = eqn.primitive.name
    p = eqn.params
    if name in _ELEMENTWISE:
        return _elementwise(eqn.primitive, p, ins)
    if name in SHAPE_OPS:
        outs = SHAPE_OPS[name](ins, p)
        return outs if eqn.primitive.multiple_results else outs[0]
    x = ins[0] if ins else None
    if name in ("reshard", "sharding_constraint"):
        # A layout annotation (e.g. `zeros_like` of a sharded array): components carry none.
        return x
    if name == "pad":
        return _pad(x, ins[1], p["padding_config"])
    if name == "dynamic_slice":
        return _dynamic_slice(x, ins[1:], p["slice_sizes"])
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
            # `cut_index`'s probe, not evaluated: its reads would add consumers, hence cuts.
            return [_const(np.int32(0))]
        return _closed(p["call"], ins)
    if name == "cond":
        index, ops = ins[0], ins[1:]
        if _is_cut(p["branches"]):  # an array program's `fusion_cut`: cut anew here
            return list(ops)
        results = [[_materialized(o) for o in _closed(br, ops)] for br in p["branches"]]
        if len(results) == 1:
            return results[0]
        return _select_branches(index, results)
    raise ScalarizeError(f"scalarize: primitive {name!r} is not supported")


_STRUCTURAL = frozenset(
    """
    broadcast_in_dim reshape squeeze expand_dims transpose rev slice concatenate stack unstack
    split pad dynamic_slice iota dot_general reduce_sum reduce_max reduce_min reduce_and reduce_or
    reduce_prod pjit jit closed_call core_call remat remat2 checkpoint custom_jvp_call
    custom_vjp_call custom_vmap_call cond reshard sharding_constraint
    """.split()
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


def equations(jaxpr, depth: int = 0):
    """``(eqn, depth)`` for every equation of ``jaxpr`` and of the jaxprs nested in its
    equations, depth first (``depth``: 0 for ``jaxpr``'s own)."""
    for e in jaxpr.eqns:
        yield e, depth
        for sub in subjaxprs(e.params):
            yield from equations(sub, depth + 1)


def _check(jaxpr) -> None:
    """Raise `ScalarizeError` up front for any primitive `_apply` does not handle."""
    for eqn, _ in equations(jaxpr):
        name = eqn.primitive.name
        if name not in _ELEMENTWISE and name not in _STRUCTURAL:
            raise ScalarizeError(f"scalarize: primitive {name!r} is not supported")


def scalarize(fn: Callable, *example_args) -> Callable:
    """``fn`` as a function over component arrays.

    Traces ``fn(*example_args)`` (one run's shapes) once; ``run(*component_args)`` takes and
    returns those pytrees with every leaf a component array (`to_components`). Raises
    `ScalarizeError` before running (`_check`).
    """
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*example_args)
    _check(closed.jaxpr)
    consts = [_Table(c) if is_table(c) else _const(c) for c in closed.consts]
    in_tree = jax.tree.structure(example_args)
    out_tree = jax.tree.structure(out_shape)

    def run(*component_args):
        leaves = in_tree.flatten_up_to(component_args)
        outs = [_materialized(o) for o in _eval(closed.jaxpr, consts, leaves)]
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


def flat_program(fn: Callable, example, index=None, cut_cone: int | None = None, columns=None):
    """``fn`` (one pytree in, one out) as a function of flat scalar component lists.

    Returns ``(run, out_struct)``: ``run`` maps ``example``'s components (`split` order) to
    the output's, each cast to its leaf's dtype; ``out_struct`` is ``jax.eval_shape(fn,
    example)``. Raises `ScalarizeError`. With an ``index`` from `cut_index`, `_eval_with_cuts`
    cuts it (``cut_cone``: the policy's unless given) and ``run.closed_for`` gives its jaxpr.
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
        cone = current().cut_cone if cut_cone is None else cut_cone
        return _eval_with_cuts(closed_for(flat), flat, index, cone, columns)

    run_flat.closed_for = closed_for
    return run_flat, out_struct


def _batched_const(x) -> bool:
    """Whether a flat program's constant is batched by an enclosing `vmap` (`_jax.batched`)."""
    return _jax.batched(x)


def batched_components(run_flat, flat: list, batched: list, dtypes=None) -> list | None:
    """Which carry components a loop of ``run_flat`` batches, given those batched at the start.

    ``None`` without ``run_flat.closed_for`` (no fusion cuts). With ``dtypes``, the program
    is taken at scalars of those types (``flat`` may then hold tangent columns).
    """
    closed_for = getattr(run_flat, "closed_for", None)
    if closed_for is None:
        return None
    if dtypes is not None:
        flat = [jax.ShapeDtypeStruct((), dt) for dt in dtypes]
    closed = closed_for(flat)
    const_b = [_batched_const(c) for c in closed.consts]
    return carry_fixed_point(closed.jaxpr, list(batched), 0, len(batched), const_b)


#: Primitives that call a jaxpr once with their operands: the flag walks (here and in
#: `so3jax._engine.masks`) walk inside them.
CALL_PRIMITIVES = frozenset(
    "pjit jit closed_call core_call custom_jvp_call custom_vjp_call remat checkpoint".split()
)

#: Primitives whose jaxpr `_eval` runs with their operands: a table passes into it whole.
_CALLS = CALL_PRIMITIVES | {"remat2", "custom_vmap_call"}


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

    From ``num_consts`` / ``num_carry`` (JAX <= 0.10) or ``ft_in`` (0.11); ``None`` where
    neither fits the body, and callers leave that loop's batching to JAX."""
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

    Values unchanged (``x + one``, ``one`` a batched zero), so that each `lax.scan` batches
    its body once (docs/engine.md, "Loops that start settled"). ``batched[i]``: whether
    ``flat[i]`` is batched already; ``dtypes`` as in `batched_components`.
    """
    flags = batched_components(run_flat, flat, batched, dtypes)
    if flags is None:
        return flat
    return [
        _batch_by(x, one) if f and not f0 else x
        for x, f, f0 in zip(flat, flags, batched, strict=True)
    ]


def split(tree) -> list:
    """The flat list of scalar components of every leaf of ``tree``."""
    return _flat_components(tree)


def join(flat, struct, lead: tuple = ()):
    """Rebuild a pytree shaped like ``struct`` from components with leading shape ``lead``
    (e.g. a scan's saved points), listed in `split` order."""
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
