"""Which values can carry a tangent: an abstract walk over a step's jaxpr.

`_tangent_masks` flags the float leaves whose tangents can be nonzero, so the derivative
programs carry tangents for those only. Nothing runs: the walk tracks element masks in NumPy.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jex_core

from .passes import scalarize as sc
from .trees import _is_float, _spec


def _depends(fn, args: list, dep: list) -> list:
    """Which outputs of ``fn(*args)`` can have a tangent from the arguments flagged in ``dep``
    (`_mask_eval` over ``fn``'s jaxpr)."""
    return _jaxpr_depends(_abstract_jaxpr(fn, args), args, dep)


def _abstract_jaxpr(fn, args: list):
    """``fn``'s jaxpr at the shapes and dtypes of ``args`` (traced once, nothing runs)."""
    return jax.make_jaxpr(fn)(*[_spec(a) for a in args]).jaxpr


def _jaxpr_depends(jaxpr, args: list, dep: list) -> list:
    """`_depends` on an already traced jaxpr of ``fn(*args)``."""
    ins = [np.full(jnp.shape(a), bool(d)) for a, d in zip(args, dep, strict=True)]
    return [bool(m.any()) for m in _mask_eval(jaxpr, ins)]


def _dot_mask(lhs, rhs, dimension_numbers) -> np.ndarray:
    """The mask of ``dot_general(lhs, rhs)``: an entry depends on what it sums."""
    (cl, cr), (bl, br) = dimension_numbers
    letters = iter("abcdefghijklmnopqrstuvwxyz")
    ls = [next(letters) for _ in range(lhs.ndim)]
    rs = [next(letters) for _ in range(rhs.ndim)]
    for i, j in zip(list(cl) + list(bl), list(cr) + list(br), strict=True):
        rs[j] = ls[i]
    free_l = [ls[i] for i in range(lhs.ndim) if i not in cl and i not in bl]
    free_r = [rs[j] for j in range(rhs.ndim) if j not in cr and j not in br]
    out = "".join([ls[i] for i in bl] + free_l + free_r)
    a, b = lhs.astype(np.int64), rhs.astype(np.int64)
    ones_a, ones_b = np.ones_like(a), np.ones_like(b)
    spec = f"{''.join(ls)},{''.join(rs)}->{out}"
    return (np.einsum(spec, a, ones_b) + np.einsum(spec, ones_a, b)) > 0


def _mask_eval(jaxpr, ins: list) -> list:
    """Element masks of ``jaxpr``'s outputs: which entries depend on the masked inputs.

    Per element, so stacked and sliced-apart attitudes stay apart. Integers, booleans and a
    ``select_n``'s predicate carry no tangent; an unknown primitive is taken whole (an
    over-approximation only).
    """
    env = dict(zip(jaxpr.invars, ins, strict=True))

    def read(v):
        if isinstance(v, jex_core.Var) and v in env:
            return env[v]
        return np.zeros(np.shape(v.aval), bool)  # literals and constants

    for e in jaxpr.eqns:
        xs = [read(v) for v in e.invars]
        name, prm = e.primitive.name, e.params
        inner = prm.get("jaxpr", prm.get("call_jaxpr"))
        inner = getattr(inner, "jaxpr", inner)
        shapes = [tuple(v.aval.shape) for v in e.outvars]
        try:
            if name in sc.SHAPE_OPS:
                outs = sc.SHAPE_OPS[name](xs, prm)
            elif name in sc._REDUCTIONS:  # an entry depends on the entries it reduces
                outs = [np.any(xs[0], axis=tuple(prm["axes"]))]
            elif name == "dot_general":
                outs = [_dot_mask(*xs, prm["dimension_numbers"])]
            elif name in sc._ELEMENTWISE:
                ys = xs[1:] if name == "select_n" else xs
                outs = [np.logical_or.reduce([np.broadcast_to(y, shapes[0]) for y in ys])]
            elif name == "cond":  # the index is an integer: no tangent
                per = [_mask_eval(b.jaxpr, xs[1:]) for b in prm["branches"]]
                outs = [np.logical_or.reduce(ms) for ms in zip(*per, strict=True)]
            elif name in sc.CALL_PRIMITIVES and isinstance(inner, jex_core.Jaxpr):
                # (not loops: one walk of a body misses what later iterations make depend)
                outs = _mask_eval(inner, xs)
            else:
                raise KeyError(name)
            outs = [np.broadcast_to(o, sh) for o, sh in zip(outs, shapes, strict=True)]
        except (KeyError, ValueError, TypeError, IndexError):  # taken whole
            hit = any(x.any() for x in xs)
            outs = [np.full(sh, hit) for sh in shapes]
        for v, m in zip(e.outvars, outs, strict=True):
            float_ = jnp.issubdtype(v.aval.dtype, jnp.inexact)
            env[v] = m if float_ else np.zeros(np.shape(m), bool)
    return [read(v) for v in jaxpr.outvars]


def _tangent_masks(
    step, P, c0, nz_P: list, nz_c: list, elements: bool = False, cache: dict | None = None
) -> tuple:
    """``(mP, mc)``: the float leaves of ``P`` and of the carry whose tangents can be nonzero.

    ``nz_P``, ``nz_c`` flag the float leaves with nonzero input tangents; a carry leaf is
    flagged if its own is or a step makes it depend on a flagged leaf (a fixed point over
    the step's jaxpr). ``elements=True`` adds, per leaf of ``(P, c0)``, the element mask from
    the same fixed point on elements (`Programs.obs_kinds`). ``cache``: the step's jaxprs by
    argument shapes (`Loop.jaxprs`), so a loop's step is traced once.
    """
    pl, pt = jax.tree.flatten(P)
    cl, ct = jax.tree.flatten(c0)

    def one_step(*leaves):
        c1 = step(
            jax.tree.unflatten(pt, leaves[: len(pl)]), jax.tree.unflatten(ct, leaves[len(pl) :])
        )
        return jax.tree.leaves(c1)

    def expand(leaves, nz):  # float-leaf flags -> flags for every leaf
        it = iter(nz)
        return [next(it) if _is_float(x) else False for x in leaves]

    dep_P, dep_c = expand(pl, nz_P), expand(cl, nz_c)
    key = (pt, ct, tuple((jnp.shape(x), jnp.result_type(x)) for x in pl + cl))
    cache = {} if cache is None else cache
    if key not in cache:  # traced once for the whole fixed point
        cache[key] = _abstract_jaxpr(one_step, pl + cl)
    jaxpr = cache[key]
    while True:
        out = _jaxpr_depends(jaxpr, pl + cl, dep_P + dep_c)
        new = [a or b for a, b in zip(dep_c, out, strict=True)]
        if new == dep_c:
            break
        dep_c = new
    mc = [d for d, x in zip(dep_c, cl, strict=True) if _is_float(x)]
    if not elements:
        return tuple(nz_P), tuple(mc)
    flags = dep_P + expand(cl, nz_c)
    ins = [np.full(jnp.shape(a), bool(d)) for a, d in zip(pl + cl, flags, strict=True)]
    while True:
        out = _mask_eval(jaxpr, ins)
        new = ins[: len(pl)] + [a | b for a, b in zip(ins[len(pl) :], out, strict=True)]
        if all(np.array_equal(a, b) for a, b in zip(new, ins, strict=True)):
            break
        ins = new
    return tuple(nz_P), tuple(mc), ins
