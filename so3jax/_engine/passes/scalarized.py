"""The ``"scalarize"`` pass's programs of one loop, and how a batch of them runs.

Program in, program out: `forward` and `jacobian` are the array programs (`Loop.fwd_array`,
`Programs.jac_array`) with step and observations scalarized (`scalarize.flat_program`), run
by `so3jax._engine.layout._dual` for a batch from `policy.batched_layout`'s size on. Each
equals the array program to round-off: ``tests/passes/test_pass_scalarize.py``. Speed:
``benchmarks/ablation.py`` (``no scalarize``), ``benchmarks/layouts.py``.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable

import jax
import jax.numpy as jnp

from .. import plan as _plan
from ..policy import current
from ..programs import Programs
from ..trees import _component_flags, _floats, _pick
from . import scalarize as sc
from .frames import FrameError, _frame_flags, _from_frames, _to_frames
from .hoist import _TRACING, _hoisted


def forward(loop: Programs, P, c0, cut=None, batched=None, one=None):
    """``loop.fwd_array(P, c0)`` over scalar components (``(B,)`` arrays under ``vmap``).

    ``cut``: a `cut_index`; ``batched``, ``one``: the batching rule's flags and a batched zero,
    to settle the carry (`scalarize.settle_batched`).
    """
    # Tables in ``P`` (`sc.is_table`) stay whole, closed over, not carried entry by entry.
    leaves, tree = jax.tree.flatten(P)
    table = [sc.is_table(x) for x in leaves]
    small = [x for x, t in zip(leaves, table, strict=True) if not t]
    tables = [x for x, t in zip(leaves, table, strict=True) if t]

    def whole(small):
        s, t = iter(small), iter(tables)
        return jax.tree.unflatten(tree, [next(t) if k else next(s) for k in table])

    ex = (small, c0)
    body, _ = sc.flat_program(lambda pc: (pc[0], loop.step(whole(pc[0]), pc[1])), ex, cut)
    obs, obs_struct = sc.flat_program(lambda pc: loop.observe(whole(pc[0]), pc[1]), ex, cut)
    flat = sc.split(ex)
    if batched is not None:
        flags = [b for b, t in zip(jax.tree.leaves(batched[0]), table, strict=True) if not t]
        flat = sc.settle_batched(body, flat, _component_flags(ex, (flags, batched[1])), one)
    flat, ys = _hoisted(functools.partial(loop.save_loop, body, obs), flat)
    _, cN = sc.join(flat, jax.eval_shape(lambda: ex))
    return sc.join(ys, obs_struct, (loop.n_save,)), cN


def jacobian(loop: Programs, mP, mc, mo, P, c0, dP, dc0, cut=None, batched=None, one=None):
    """`Programs.jac_array` as a scalarized program: tangent components are ``(n,)`` arrays.

    Carry leaves flagged `FRAME` in ``mc`` carry `Frame` tangents inside (`passes.frames`),
    dense where a `FrameError` names them; in and out, tangents are dense.
    """
    while any(_frame_flags(mc)):
        try:
            out = _jacobian(loop, mP, mc, mo, P, c0, dP, dc0, cut, batched, one)
            _plan.note("frames", rotations=sum(_frame_flags(mc)))
            return out
        except FrameError as e:
            at = [i for i, m in enumerate(mc) if m]
            dense = {at[j] for j in e.indices}
            mc = tuple(True if i in dense else m for i, m in enumerate(mc))
    _plan.note("frames", rotations=0)
    return _jacobian(loop, mP, mc, mo, P, c0, dP, dc0, cut, batched, one)


def _jacobian(loop, mP, mc, mo, P, c0, dP, dc0, cut, batched, one):
    fr = _frame_flags(mc)
    if any(fr):
        dc0 = _to_frames(_pick(mc, _floats(c0)), list(dc0), fr)
    col = jax.tree.map(lambda a: a[0], (dP, dc0))  # one column: the example
    ex = (P, c0) + col
    n_primal = len(sc.split((P, c0)))
    n_tangent = sum(math.prod(jnp.shape(a)) for a in jax.tree.leaves(col))
    n = jnp.shape(jax.tree.leaves((dP, dc0))[0])[0]
    # One column: `columns_outside` vmaps the columns around it; its cuts count them.
    columns = None
    if n == 1 and _TRACING.get()[0] >= current().column_cuts_from:
        columns = [False] * n_primal + [True] * n_tangent
    tstep = functools.partial(loop.tangent_step, mP, mc)
    body, _ = sc.flat_program(tstep, ex, cut, columns=columns)
    tobs, tobs_struct = sc.flat_program(
        functools.partial(loop.observation_tangents, mP, mc, mo), ex, cut, columns=columns
    )
    obs, obs_struct = sc.flat_program(lambda x: loop.observe(x[0], x[1]), ex, cut)
    flat0 = sc.split((P, c0)) + jax.vmap(sc.split)((dP, dc0))
    if n == 1:  # one column (`columns_outside`): scalar tangent components
        vbody = body

        def observe(flat):
            return obs(flat), jax.tree.map(lambda a: a[None], tobs(flat))

        flat0 = flat0[:n_primal] + [x[0] for x in flat0[n_primal:]]
    else:
        axes = [None] * n_primal + [0] * n_tangent
        vbody = jax.vmap(body, in_axes=(axes,), out_axes=axes)
        vtobs = jax.vmap(tobs, in_axes=(axes,))

        def observe(flat):
            return obs(flat), vtobs(flat)

    if batched is not None:  # a column's components: the body's example
        flags = _component_flags(ex, batched)
        flat0 = sc.settle_batched(body, flat0, flags, one, [jnp.result_type(x) for x in flat0])
    flat, (ys, dys) = _hoisted(functools.partial(loop.save_loop, vbody, observe), flat0)
    _, cN = sc.join(flat[:n_primal], jax.eval_shape(lambda: (P, c0)))
    if n == 1:
        flat = flat[:n_primal] + [x[None] for x in flat[n_primal:]]
    _, dcN = sc.join(flat[n_primal:], jax.eval_shape(lambda: col), (n,))
    if any(fr):
        dcN = _from_frames(_pick(mc, _floats(cN)), list(dcN), fr)
    ys = sc.join(ys, obs_struct, (loop.n_save,))
    return ys, cN, sc.join(dys, tobs_struct, (loop.n_save, n)), dcN


def or_array(loop: Programs) -> Callable:
    """The scalarized forward program, or the array one (with a warning) if it cannot be."""

    def fwd(P, c0):
        try:
            return forward(loop, P, c0)
        except sc.ScalarizeError as e:
            warnings.warn(f"{e}; running the array program instead", stacklevel=4)
            return loop.fwd_array(P, c0)

    return fwd


def columns_outside(runs: Callable, args, in_batched, in_cols: list, out_cols: list):
    """``runs(*args)`` (a batch of scalarized Jacobian programs, or their ``jvp``) with
    the column axis of the Jacobian's tangents outside the runs' axis.

    One column runs under ``runs`` and the columns are a ``vmap`` around it: tangents are
    ``(n, B)``, the primal ``(B,)``, computed once (docs/engine.md, "The one-pass
    Jacobian"). ``in_cols`` / ``out_cols``: per leaf of ``args`` / of the output, the axis
    of the columns in one run's leaf (``None``: none).
    """
    leaves, treedef = jax.tree.flatten(args)
    flags = jax.tree.leaves(in_batched)
    axes = [None if c is None else c + int(b) for c, b in zip(in_cols, flags, strict=True)]
    out_tree = []

    def column(*cols):
        it = iter(cols)
        pairs = zip(leaves, axes, strict=True)
        one = [x if a is None else jnp.expand_dims(next(it), a) for x, a in pairs]
        outs, tree = jax.tree.flatten(runs(*jax.tree.unflatten(treedef, one)))
        out_tree.append(tree)
        # every output is batched over the runs (axis 0), so a run's axis c is c + 1
        pairs = zip(outs, out_cols, strict=True)
        return [o if c is None else jnp.squeeze(o, c + 1) for o, c in pairs]

    outs = jax.vmap(
        column,
        in_axes=tuple(a for a in axes if a is not None),
        out_axes=[None if c is None else c + 1 for c in out_cols],
    )(*[x for x, a in zip(leaves, axes, strict=True) if a is not None])
    return jax.tree.unflatten(out_tree[0], outs)


def column_count(args, in_batched, out_tree) -> int:
    """The number of tangent columns of a batched call of the Jacobian program."""
    in_cols, _ = jacobian_columns(args, out_tree)
    pairs = zip(jax.tree.leaves(args), jax.tree.leaves(in_batched), in_cols, strict=True)
    return next((jnp.shape(x)[c + int(b)] for x, b, c in pairs if c is not None), 0)


def jacobian_columns(args, out_tree) -> tuple[list, list]:
    """`columns_outside`'s ``in_cols`` and ``out_cols`` for ``(P, c0, dP, dc) -> (ys, cN, dys,
    dcN)``: columns on axis 0 of ``dP``, ``dc`` and ``dcN``, axis 1 of ``dys``."""
    n_in = [len(jax.tree.leaves(a)) for a in args]
    n_out = [t.num_leaves for t in out_tree.children()]
    in_cols = [None] * (n_in[0] + n_in[1]) + [0] * (n_in[2] + n_in[3])
    out_cols = [None] * (n_out[0] + n_out[1]) + [1] * n_out[2] + [0] * n_out[3]
    return in_cols, out_cols
