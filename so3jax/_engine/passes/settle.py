"""The ``"settle"`` pass: each loop starts where JAX's fixed point over its carry ends.

Under ``vmap`` JAX finds which components of a ``scan``'s carry become batched, and under
``jvp`` which carry tangents become nonzero (under ``grad`` its partial evaluator finds
the unknown ones the same way), by transforming the loop's body again until nothing
changes: two passes over a body whose carry starts partly unbatched or with symbolic
zero tangents, and every loop nested in that body once more per pass. This pass takes
the same fixed point on flags first and starts the loop there, so that JAX transforms
each body once:

- `batched_carries`: the array program under ``vmap`` (`so3jax._engine.layout._Traced`)
  batches, before each loop, the carry components its body would batch (what stays
  unbatched, such as the reference attitude a batch shares, stays so);
- `carry_tangents`: JAX's ``jvp`` of the checkpointed program (the ``"checkpointed
  jvp"`` strategies of `so3jax._engine.derivatives`) starts each initial carry leaf that
  a step gives a nonzero tangent with a zero tangent instead of a symbolic one;
- `jacobian_tangents`: the same for the Jacobian program's second derivatives.

The program and its values are unchanged; tracing and lowering are shorter
(``benchmarks/ablation.py``'s tracing times). With the pass off each function returns
its inputs. Each records a ``"settle"`` entry in the plan (`so3jax.explain`) where it
starts a loop elsewhere than JAX would.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import numpy as np

from .. import plan as _plan
from ..masks import _tangent_masks
from ..policy import current
from ..trees import _is_float, _pick, _zero_like_tangent
from . import scalarize as sc


def batched_carries(body, split: tuple, ins: list, bs: list, batch: Callable):
    """``(ins, bs)`` of a ``scan`` equation with its carry batched as its body's fixed
    point leaves it. ``body``: the loop's body jaxpr; ``split``: its ``(num_consts,
    num_carry)``; ``bs``: which operands are batched; ``batch(x)``: ``x`` batched."""
    if not current().on("settle"):
        return ins, bs
    nc, ncar = split
    settled = sc.carry_fixed_point(body, bs, nc, ncar)
    ins, bs = list(ins), list(bs)
    moved = 0
    for i, (now, then) in enumerate(zip(bs[nc : nc + ncar], settled, strict=True)):
        if then and not now:
            ins[nc + i], bs[nc + i] = batch(ins[nc + i]), True
            moved += 1
    if moved:
        _plan.note("settle", what="batched carry", components=moved)
    return ins, bs


def carry_tangents(step, primals, p_leaves, t_leaves, nz, cache=None) -> tuple[list, list]:
    """``(t_leaves, nz)`` with a zero tangent, not a symbolic one, for each initial carry
    leaf that a step gives a nonzero tangent (`_tangent_masks`), flagged nonzero.

    ``primals`` is ``(P, c0)``, ``p_leaves`` its leaves, ``t_leaves`` their tangents and
    ``nz`` whether each is nonzero. The zero is computed from an input tangent
    (`_zero_like_tangent`), so that ``grad``'s partial evaluator sees it as unknown too.
    ``cache``: `_tangent_masks`'.
    """
    if not current().on("settle"):
        return t_leaves, nz
    P, c0 = primals
    n_P = len(jax.tree.leaves(P))
    floats = [_is_float(x) for x in p_leaves]
    nz_P, nz_c = _pick(floats[:n_P], nz[:n_P]), _pick(floats[n_P:], nz[n_P:])
    sources = [t for t, z, f in zip(t_leaves, nz, floats, strict=True) if z and f and t.size]
    if not sources or all(nz_c):
        return t_leaves, nz
    _, mc = _tangent_masks(step, P, c0, nz_P, nz_c, cache=cache)
    it = iter(mc)
    t_leaves, nz = list(t_leaves), list(nz)
    moved = 0
    for i in range(n_P, len(p_leaves)):
        if floats[i] and next(it) and not nz[i]:
            t_leaves[i], nz[i] = _zero_like_tangent(p_leaves[i], sources[0]), True
            moved += 1
    if moved:
        _plan.note("settle", what="carry tangents", leaves=moved)
    return t_leaves, nz


def jacobian_tangents(loop, mP, mc, primals, p_leaves, t_leaves, nz):
    """`carry_tangents` for the Jacobian program (`Programs.jac_array`), whose arguments
    ``(P, c0, dP, dc0)`` are a loop's parameters ``(P, dP)`` and its carry ``(c0, dc0)``:
    the carry tangents of second derivatives (`so3jax._engine.layout._dual_jvp`)."""
    if not current().on("settle"):
        return t_leaves, nz
    sizes = [len(jax.tree.leaves(x)) for x in primals]
    a, b, c = np.cumsum(sizes)[:3].tolist()
    order = [*range(a), *range(b, c), *range(a, b), *range(c, len(p_leaves))]
    P, c0, dP, dc0 = primals
    t, z = carry_tangents(
        functools.partial(loop.jac_step, mP, mc),
        ((P, dP), (c0, dc0)),
        [p_leaves[i] for i in order],
        [t_leaves[i] for i in order],
        [nz[i] for i in order],
    )
    back = np.argsort(order).tolist()
    return [t[i] for i in back], [z[i] for i in back]
