"""The ``"settle"`` pass: each loop starts where JAX's fixed point over its carry ends.

Program in, program out: each function takes the fixed point JAX would iterate a ``scan``
body to (its carry's batched or nonzero-tangent flags; docs/engine.md, "Loops that start
settled") on flags first and starts the loop there, so JAX transforms each body once. With
the pass off each returns its inputs; each notes ``"settle"`` in the plan where it acts.
Values unchanged: ``tests/passes/test_pass_settle.py``; tracing shorter:
``benchmarks/ablation.py``'s tracing times.
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
    """``(ins, bs)`` of a ``scan`` equation (the array program under ``vmap``,
    `so3jax._engine.layout._Traced`) with its carry batched as its body's fixed point leaves
    it. ``split``: ``(num_consts, num_carry)``; ``bs``: which operands are batched;
    ``batch(x)``: ``x`` batched."""
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
    """``(t_leaves, nz)`` for JAX's ``jvp`` of the checkpointed program
    (`so3jax._engine.derivatives`), with a zero tangent, flagged nonzero, for each initial
    carry leaf a step gives a nonzero tangent (`_tangent_masks`, with its ``cache``).

    ``primals``: ``(P, c0)``, with leaves ``p_leaves``, tangents ``t_leaves``, nonzero flags
    ``nz``. The zero is made from an input tangent (`_zero_like_tangent`): unknown to ``grad``
    too.
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
    ``(P, c0, dP, dc0)`` are parameters ``(P, dP)`` and carry ``(c0, dc0)``: for second
    derivatives (`so3jax._engine.layout._dual_jvp`)."""
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
