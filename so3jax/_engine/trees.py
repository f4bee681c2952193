"""Pytrees split into float leaves (differentiable) and the rest; tangents and batch axes.

Helpers every engine program shares: flagged leaves, tangent trees with ``float0`` zeros,
unit tangent columns, and outputs batched wherever an input is (`_batched_with`, `_front`).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap
from jax.custom_derivatives import SymbolicZero


def _is_float(x) -> bool:
    return jnp.issubdtype(jnp.result_type(x), jnp.inexact)


def _spec(x) -> jax.ShapeDtypeStruct:
    """The shape and dtype of ``x``."""
    return jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x))


def _floats(tree) -> list:
    return [x for x in jax.tree.leaves(tree) if _is_float(x)]


def _with_floats(tree, floats):
    leaves, treedef = jax.tree.flatten(tree)
    it = iter(floats)
    new = [next(it) if _is_float(x) else x for x in leaves]
    return jax.tree.unflatten(treedef, new)


def _tangent_tree(primal, float_tangents):
    """A tangent pytree for ``primal``: the given float tangents, float0 zeros elsewhere."""
    leaves, treedef = jax.tree.flatten(primal)
    it = iter(float_tangents)
    new = [next(it) if _is_float(x) else np.zeros(jnp.shape(x), jax.dtypes.float0) for x in leaves]
    return jax.tree.unflatten(treedef, new)


def _fill(nz: list, xs, others: list) -> list:
    """``others`` with the entries flagged in ``nz`` replaced, in order, by ``xs``."""
    it = iter(xs)
    return [next(it) if z else o for z, o in zip(nz, others, strict=True)]


def _pick(mask, xs) -> list:
    """The entries of ``xs`` flagged in ``mask``."""
    return [x for m, x in zip(mask, xs, strict=True) if m]


def _tangent_leaves(tangents) -> tuple[list, list]:
    """A ``custom_jvp`` rule's tangents (``symbolic_zeros=True``) as leaves, and per leaf
    whether it is nonzero (not a `SymbolicZero`)."""
    t_leaves = jax.tree.leaves(tangents, is_leaf=lambda t: isinstance(t, SymbolicZero))
    return t_leaves, [not isinstance(t, SymbolicZero) for t in t_leaves]


def _masked_tangents(nz, xs, mP, mc, pf, cf, lead=()) -> tuple[list, list]:
    """The tangents a masked tangent program takes: ``(dP, dc)``.

    ``xs``: the nonzero input tangents (float leaves flagged in ``nz``, parameters ``pf``
    then carry ``cf``), each with leading shape ``lead``. A masked carry leaf without one
    starts at zero.
    """
    full = _fill(nz, xs, [None] * len(nz))
    dP = _pick(mP, full[: len(pf)])
    dc = [
        jnp.zeros(tuple(lead) + jnp.shape(x), jnp.result_type(x)) if d is None else d
        for x, d in zip(_pick(mc, cf), _pick(mc, full[len(pf) :]), strict=True)
    ]
    return dP, dc


@jax.custom_jvp
@custom_vmap
def _front(x):
    """``x`` unchanged; under ``vmap``, each batched leaf with its batch axis first."""
    return x


@_front.fun.def_vmap
def _front_vmap(axis_size, in_batched, x):  # `custom_vmap` hands the rule axis 0
    return x, in_batched[0]


@_front.defjvp
def _front_jvp(primals, tangents):  # JAX matches a rule's tangent axes to its primal's
    return _front(primals[0]), tangents[0]


def _batch_by(x, one):
    """``x`` made batched by adding ``one``, a batched zero (values unchanged)."""
    x = jnp.asarray(x)
    if x.dtype == jnp.bool_:
        return jnp.logical_or(x, one != 0)
    if jnp.issubdtype(x.dtype, jnp.number):
        return x + one.astype(x.dtype)
    return x  # (a key, say: JAX's own fixed point batches it if it must)


def _component_flags(example, batched) -> list:
    """Per scalar component of ``example`` (in `sc.split` order), its leaf's flag in ``batched``
    (one flag per leaf, as a `custom_vmap` rule's ``in_batched``)."""
    return [
        b
        for leaf, b in zip(jax.tree.leaves(example), jax.tree.leaves(batched), strict=True)
        for _ in range(math.prod(jnp.shape(leaf)))
    ]


def _batched_with(out, inputs):
    """``out`` with a zero from every numeric leaf of ``inputs`` added to each numeric leaf
    (values unchanged): under ``vmap``, every output is batched wherever an input is.

    A ``custom_jvp`` function and its rule must batch the same outputs: `_dual` batches
    every output, JAX's ``jvp`` only those a batched input moves (not the run's times:
    tests/test_engine.py::test_derivatives_of_a_jitted_batch_through_more_than_8_scalars).
    The zero is ``where(False, ...)``, not ``0 * x``, so an infinite input stays out.
    """
    srcs = [
        jnp.ravel(x)[0]
        for x in jax.tree.leaves(inputs)
        if jnp.size(x) and jnp.issubdtype(jnp.result_type(x), jnp.number)
    ]
    if not srcs:
        return out
    zero = functools.reduce(jnp.add, [jnp.where(False, s, 0).astype(jnp.int32) for s in srcs])
    return jax.tree.map(lambda x: _batch_by(x, zero), out)


def _zero_like_tangent(x, source):
    """Zeros shaped like ``x``, computed from the tangent ``source`` (values unused)."""
    s = jnp.ravel(source)[0]
    return jnp.broadcast_to(jnp.where(False, s, 0).astype(jnp.result_type(x)), jnp.shape(x))


def _unit_columns(xs: list) -> list:
    """The ``n`` unit tangents of the arrays ``xs`` (``n`` scalars in all), batched:
    for each array, ``(n,) + shape`` with one 1 per column, in the order of ``ravel``."""
    sizes = [math.prod(jnp.shape(x)) for x in xs]
    n = sum(sizes)
    starts = np.cumsum([0] + sizes[:-1]).tolist()
    return [
        jnp.eye(n, dtype=jnp.result_type(x))[:, a : a + k].reshape((n,) + jnp.shape(x))
        for x, a, k in zip(xs, starts, sizes, strict=True)
    ]


def _floats_with_zeros(tangents, primals) -> list:
    """Tangents of the float leaves of ``primals`` (symbolic zeros kept)."""
    t_leaves = jax.tree.leaves(tangents, is_leaf=lambda x: isinstance(x, SymbolicZero))
    p_leaves = jax.tree.leaves(primals)
    return [t for t, p in zip(t_leaves, p_leaves, strict=True) if _is_float(p)]
