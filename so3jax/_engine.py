"""The execution engine: how every fixed-step run executes.

`simulate`, `rollout_cost` / `expected_cost`, `sweep` and `tune` all step a
carry with a pure step function and save observations every ``save_every``
steps. They hand that loop to `run`, which picks the program for what the call
is, with no flag for the user to know:

- **a single run** executes the array program: ``lax.scan`` over the step as
  written (3-vectors and 3x3 matrices), the fastest layout for one trajectory. On
  CPU the array programs (this one and small batches') cut their derivative rules,
  chains of updates and the Runge-Kutta stages that later stages read where XLA
  would recompute them in every element of their consumers
  (`so3jax._scalarize.array_cut_index`);
- **a batch under ``vmap``** of `BATCHED_LAYOUT` runs or more executes the scalarized
  program (`so3jax._scalarize`): every scalar component of the carry is its
  own contiguous ``(B,)`` array and a step is a few hundred small elementwise
  kernels (a structure-of-arrays layout); a smaller batch runs the array
  program, vmapped. On a GPU the thresholds are `GPU_LAYOUT`'s: below them the
  array program, which compiles faster. The switch is a
  `jax.custom_batching.custom_vmap` rule, so nested ``vmap`` (gains x
  attitudes) and ``vmap`` inside ``jit`` take it. On CPU the
  rule also hands the program an unbatched index
  (`so3jax._scalarize.cut_index`) with which it cuts fusion where XLA would
  recompute shared values once per consumer (`so3jax._scalarize.fusion_cut`);
- **every loop, on a CPU**, compiles as one kernel (`_hoisted`): XLA's runtime
  otherwise dispatches each fused kernel of a step on its own and hands them between
  the threads of its pool. Loops
  with a dot or another primitive XLA's older emitter refuses, batches whose largest
  leaf exceeds `HOIST_MAX_BYTES`, sharded programs and second derivatives' programs
  run as before (``SO3JAX_HOIST_LOOPS=0`` turns it off; so does a jaxlib outside
  `HOIST_VERIFIED`, the releases tested). The array layout's derivative
  programs are hoisted with their small reductions written out term by term
  (`_unrolled`);
- **a differentiated run** hangs its derivatives on one ``jax.custom_jvp``.
  Through at most `FORWARD_JACOBIAN_MAX` differentiated scalars (two gains,
  six per-axis gains, gains and initial rates) the run computes its value and
  its Jacobian in **one pass**: the primal once, the unit tangents batched over
  it as columns (`_Loop.jac_array` / `_Loop.jac_scalar`, scalarized for
  large batches, with the columns the outer axis of every tangent
  component: `_columns_outside`; on a CPU a large batch runs in tiles of a few
  dozen runs whose values stay in cache, `BATCH_TILE`). In the scalarized layout a
  rotation's tangent is three numbers, ``xi`` in ``dR = R hat(xi)``, not nine
  (`so3jax._frames`, `FRAME_TANGENTS`); a step that gives a dense tangent (LGVI)
  keeps nine. The tangent is that Jacobian times the input
  tangent: ``jacfwd`` reads the columns, and ``grad`` is JAX's transpose of
  the contraction, with nothing stored per step beyond the saved points and
  nothing recomputed. Through more scalars (DiffTune's twelve gains) both modes
  are JAX's own ``jvp`` of the *checkpointed* array program (segments of about
  ``sqrt(n_steps)`` steps under `jax.checkpoint`), transposed by JAX in
  reverse mode, whose memory grows like ``sqrt(n_steps)``. JAX transposes it
  with symbolic zeros for the observations a cost does not use and prunes
  their backward pass, which a custom transpose (``program="adjoint"``) cannot.
  ``program="autodiff"`` is JAX's own derivative of the checkpointed array
  program throughout (the reference).

Second derivatives (``jax.hessian``, ``jvp`` of ``grad``, and higher) differentiate
the programs the rules run: each is a `_dual`, whose own derivative is JAX's ``jvp``
of the array program for one run and, under ``vmap``, the ``jvp`` of the program a batch
runs (``BATCHED_LAYOUT["jvp"]``; a Jacobian program's with its columns outside the
runs, as the program itself), behind a ``linear_call`` (`so3jax._linear_call`) whose
transpose runs that program once per unit tangent through at most
`FORWARD_JACOBIAN_MAX` scalars (`_transpose_by_columns`) and is JAX's transpose of the
array program through more; the value beside it is the `_dual` itself (`_dual_jvp`).

``program="adjoint"`` runs the engine's tangent program in forward mode (a scan
of ``jax.jvp`` of one step; it carries tangents only for the leaves that can have one,
`_tangent_masks`: with the gains differentiated, the reference attitude, time and
status stay out) and makes reverse mode a **discrete adjoint** whatever the number of
inputs (a backward scan of ``jax.vjp`` of one step and its observation, with the
states recomputed from checkpoints every ``K ~ sqrt(n_steps)`` steps), exact to
round-off against plain autodiff. The linear maps with a custom transpose are
so3jax's own primitive (`so3jax._linear_call`), which batches, so ``vmap(grad(...))``
and ``jacfwd`` work through it; JAX's rule tables are left as they are. Both
derivative programs exist in the scalarized layout too (`BATCHED_LAYOUT`). The
adjoint stays in the array layout: XLA on CPU compiles the scalarized adjoint step
(thousands of scalar operations) far more slowly than it runs.

Every program exists in both layouts (array and scalarized); a step with a
primitive the scalarizer does not handle (a loop, dynamic indexing) runs the
array program in every case, with a warning. The design and its measurements:
``docs/engine.md`` and ``docs/performance.md``.

References: A. Griewank, A. Walther, *Evaluating Derivatives*, SIAM 2008
(the vector forward mode of the one-pass Jacobian and discrete adjoints, ch. 3;
checkpointing, ch. 12); JAX's ``linear_call``
docstring (a linear function with a custom transpose).
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import math
import os
import warnings
import weakref
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap
from jax.custom_derivatives import SymbolicZero
from jax.extend import core as jex_core

from . import _jax, _linear_call, _plan, _scalarize as sc
from ._frames import Frame, FrameError, dense as frames_dense, frame_jvp
from ._linear_call import linear_call
from ._so3 import _mm, _mT, _vee

__all__ = ["run", "checkpoint_length"]


# --------------------------------------------------------------------------
# pytrees split into float leaves (differentiable) and the rest
# --------------------------------------------------------------------------


def _is_float(x) -> bool:
    return jnp.issubdtype(jnp.result_type(x), jnp.inexact)


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

    ``xs`` are the nonzero input tangents (the float leaves flagged in ``nz``,
    parameters ``pf`` first, then carry ``cf``), each with leading shape
    ``lead``. A masked carry leaf without an input tangent starts at zero.
    """
    full = _fill(nz, xs, [None] * len(nz))
    dP = _pick(mP, full[: len(pf)])
    dc = [
        jnp.zeros(tuple(lead) + jnp.shape(x), jnp.result_type(x)) if d is None else d
        for x, d in zip(_pick(mc, cf), _pick(mc, full[len(pf) :]), strict=True)
    ]
    return dP, dc


# ---------------------------------------------------------------------------
# Attitude tangents as three numbers (`so3jax._frames`)
# ---------------------------------------------------------------------------

#: A carry mask's flag for a leaf whose tangent the Jacobian programs carry as a
#: `Frame`: ``xi`` of shape ``shape[:-2] + (3,)`` for ``dR = R hat(xi)``.
FRAME = 2


def _frame_flags(mc) -> list:
    """Per masked carry leaf, whether its tangent is a `Frame`."""
    return [m == FRAME for m in mc if m]


def _dense_mask(mc) -> tuple:
    """``mc`` with its `FRAME` flags read as plain ones (nine numbers per rotation)."""
    return tuple(bool(m) for m in mc)


def _to_frames(cm, dc, fr) -> list:
    """Dense rotation tangents (``n`` columns in front) as `Frame` ``xi``: ``vee(R^T dR)``
    (exact for the zero tangents the Jacobian programs start from)."""
    return [_vee(_mm(_mT(R), d)) if f else d for R, d, f in zip(cm, dc, fr, strict=True)]


def _from_frames(cm, dc, fr) -> list:
    """`Frame` ``xi`` (``n`` columns in front) as dense tangents ``R hat(xi)``."""
    return [frames_dense(R, Frame(d)) if f else d for R, d, f in zip(cm, dc, fr, strict=True)]


def _jvp_with_frames(fn, Pm, cm, dP, dc, fr):
    """`frame_jvp` of ``fn(Pm, cm)`` (a pytree out) with the carry tangents flagged in
    ``fr`` given as `Frame` ``xi``: ``(out leaves, their tangents, out treedef)``."""
    tree = []

    def flat(*args):
        leaves, treedef = jax.tree.flatten(fn(list(args[: len(Pm)]), list(args[len(Pm) :])))
        tree.append(treedef)
        return leaves

    tin = list(dP) + [Frame(d) if f else d for d, f in zip(dc, fr, strict=True)]
    outs, touts = frame_jvp(flat, list(Pm) + list(cm), tin)
    return outs, touts, tree[-1]


def _frame_step(g, Pm, cm, dP, dc, fr):
    """``(dc1, c1)``: `_Loop._tstep`'s ``jvp`` of ``g`` (``-> (masked carry floats, c1)``)
    with `Frame` carry tangents.

    Raises `FrameError` naming the leaves whose tangent came out dense."""
    outs, touts, treedef = _jvp_with_frames(g, Pm, cm, dP, dc, fr)
    n = len(fr)  # the masked carry floats come first
    dc1, bad = [], []
    for i, (f, o, t) in enumerate(zip(fr, outs[:n], touts[:n], strict=True)):
        if f and isinstance(t, Frame) and not t.left:
            dc1.append(t.xi.astype(jnp.result_type(o)))
        elif f and t is None:
            dc1.append(jnp.zeros(jnp.shape(o)[:-2] + (3,), jnp.result_type(o)))
        elif f:
            bad.append(i)
        else:
            dc1.append(jnp.zeros_like(o) if t is None else frames_dense(o, t))
    if bad:
        raise FrameError(bad)
    return dc1, jax.tree.unflatten(treedef, outs)[1]


def _frame_observe(o, Pm, cm, dP, dc, fr):
    """`_Loop._tobs`'s tangent of ``o`` with `Frame` carry tangents (dense outputs)."""
    outs, touts, treedef = _jvp_with_frames(o, Pm, cm, dP, dc, fr)
    tan = [
        jnp.zeros_like(x) if t is None else frames_dense(x, t)
        for x, t in zip(outs, touts, strict=True)
    ]
    return jax.tree.unflatten(treedef, tan)


#: An observation's kind in the Jacobian programs (`_Loop.obs_kinds`): no tangent (not
#: computed; zeros outside), a dense one, or a `Frame` ``xi`` (right, left), three numbers
#: per rotation that `_jacobian_jvp` turns dense after the loop.
OBS_ZERO, OBS_DENSE, OBS_RIGHT, OBS_LEFT = 0, 1, 2, 3


def _obs_kind(x, t) -> int:
    """The kind of an observation ``x`` whose tangent `frame_jvp` gave as ``t``."""
    if t is None:
        return OBS_ZERO
    if FRAME_TANGENTS and isinstance(t, Frame):
        return OBS_LEFT if t.left else OBS_RIGHT
    return OBS_DENSE


def _obs_tangent(x, t, kind: int):
    """The tangent ``t`` of the observation ``x`` (``None``, an array or a `Frame`) as its
    ``kind`` stores it: dense, or ``xi`` (``vee(R^T dR)`` or ``vee(dR R^T)`` from a dense one,
    which for a rotation ``R`` is ``dR`` exactly in exact arithmetic)."""
    if kind == OBS_DENSE:
        return jnp.zeros_like(x) if t is None else frames_dense(x, t)
    left = kind == OBS_LEFT
    if t is None:
        return jnp.zeros(jnp.shape(x)[:-2] + (3,), jnp.result_type(x))
    if isinstance(t, Frame) and t.left == left:
        return t.xi.astype(jnp.result_type(x))
    d = frames_dense(x, t)
    return _vee(_mm(d, _mT(x)) if left else _mm(_mT(x), d))


def _with_frames(mc, c0, nz_c) -> tuple:
    """``mc`` with `FRAME` for each masked carry leaf that may carry a `Frame`: rotation-
    shaped, without an input tangent (it starts at zero, ``R hat(0)`` for any ``R``).

    Whether a step keeps it a frame is found when the scalarized Jacobian program is
    traced (`_Loop.jac_scalar`, which falls back to nine numbers for a leaf whose tangent
    comes out dense, such as LGVI's); the array layout always carries nine.
    """
    return tuple(
        FRAME if FRAME_TANGENTS and m and not z and tuple(jnp.shape(x)[-2:]) == (3, 3) else m
        for m, x, z in zip(mc, _floats(c0), nz_c, strict=True)
    )


def _depends(fn, args: list, dep: list) -> list:
    """Which outputs of ``fn(*args)`` can have a tangent from the arguments flagged in ``dep``.

    An abstract walk over ``fn``'s jaxpr (nothing runs) that tracks every
    array element: a step that stacks the body's and the reference's attitudes
    into one array and slices them apart again keeps them apart here (a walk
    over whole arrays would not). Integer and boolean values carry no tangent,
    nor does the predicate of a ``select_n`` (a freeze on failure selects
    between states by a flag computed from all of them). Unknown primitives
    are taken whole, which can only over-approximate.
    """
    return _jaxpr_depends(_abstract_jaxpr(fn, args), args, dep)


def _abstract_jaxpr(fn, args: list):
    """``fn``'s jaxpr at the shapes and dtypes of ``args`` (traced once, nothing runs)."""
    spec = [jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a)) for a in args]
    return jax.make_jaxpr(fn)(*spec).jaxpr


def _jaxpr_depends(jaxpr, args: list, dep: list) -> list:
    """`_depends` on an already traced jaxpr of ``fn(*args)``."""
    ins = [np.full(jnp.shape(a), bool(d)) for a, d in zip(args, dep, strict=True)]
    return [bool(m.any()) for m in _mask_eval(jaxpr, ins)]


_SHAPE_OPS = {
    "reshape": lambda x, p: np.reshape(x, p["new_sizes"]),
    "squeeze": lambda x, p: np.squeeze(x, axis=tuple(p["dimensions"])),
    "expand_dims": lambda x, p: np.expand_dims(x, tuple(p["dimensions"])),
    "transpose": lambda x, p: np.transpose(x, p["permutation"]),
    "rev": lambda x, p: np.flip(x, tuple(p["dimensions"])),
    "slice": lambda x, p: x[
        tuple(
            slice(a, b, None if p["strides"] is None else p["strides"][i])
            for i, (a, b) in enumerate(zip(p["start_indices"], p["limit_indices"], strict=True))
        )
    ],
    "broadcast_in_dim": lambda x, p: np.broadcast_to(
        np.expand_dims(
            x, tuple(i for i in range(len(p["shape"])) if i not in p["broadcast_dimensions"])
        ),
        p["shape"],
    ),
    "reduce_sum": lambda x, p: np.any(x, axis=tuple(p["axes"])),
    "reduce_max": lambda x, p: np.any(x, axis=tuple(p["axes"])),
    "reduce_min": lambda x, p: np.any(x, axis=tuple(p["axes"])),
}


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
    """Element masks of ``jaxpr``'s outputs: which entries depend on the masked inputs."""
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
            if name in _SHAPE_OPS:
                outs = [np.asarray(_SHAPE_OPS[name](xs[0], prm), bool)]
            elif name == "concatenate":
                outs = [np.concatenate(xs, axis=prm["dimension"])]
            elif name == "stack":
                outs = [np.stack(xs, axis=prm["axis"])]
            elif name == "split":
                cuts = np.cumsum(prm["sizes"])[:-1]
                outs = np.split(xs[0], cuts, axis=prm["axis"])
            elif name == "dot_general":
                outs = [_dot_mask(*xs, prm["dimension_numbers"])]
            elif name in sc._ELEMENTWISE:
                ys = xs[1:] if name == "select_n" else xs
                outs = [np.logical_or.reduce([np.broadcast_to(y, shapes[0]) for y in ys])]
            elif name == "cond":  # the index is an integer: no tangent flows through it
                per = [_mask_eval(b.jaxpr, xs[1:]) for b in prm["branches"]]
                outs = [np.logical_or.reduce(ms) for ms in zip(*per, strict=True)]
            elif name in sc.CALL_PRIMITIVES and isinstance(inner, jex_core.Jaxpr):
                # (Loops are taken whole below: a loop's body walked once would miss
                # what a later iteration makes depend.)
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


def _tangent_masks(step, P, c0, nz_P: list, nz_c: list, elements: bool = False) -> tuple:
    """Float leaves of ``P`` and of the carry whose tangents can be nonzero.

    ``nz_P``, ``nz_c`` flag the float leaves with nonzero input tangents. A
    carry leaf is masked if its initial tangent is nonzero or a step makes it
    depend on a masked leaf (a fixed point over the step's jaxpr): with the
    gains differentiated, the reference attitude, the time and the status stay
    out of the tangent program.

    ``elements=True`` adds a third result: per leaf of ``(P, c0)`` (every leaf), the
    element mask of what can have a nonzero tangent, from the same fixed point run
    on elements. It is finer than the leaf flags: a body and a reference attitude
    stacked in one carry leaf are told apart (`_Loop.obs_kinds`).
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
    jaxpr = _abstract_jaxpr(one_step, pl + cl)  # traced once for the whole fixed point
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


def _segment_blocks(n: int, target: int) -> int:
    """Blocks per segment: a divisor of ``n`` within 2x of ``target`` if there is one.

    A divisor needs no padded tail (whose masks cost a select per carry leaf
    and step); otherwise ``target`` itself, and the last segment is padded.
    """
    target = max(1, min(n, target))
    for d in sorted(
        range(max(1, target // 2), min(n, 2 * target) + 1), key=lambda d: abs(d - target)
    ):
        if n % d == 0:
            return d
    return target


def checkpoint_length(n_steps: int) -> int:
    """Steps per checkpointed segment: about ``sqrt(n_steps)``."""
    return max(1, math.ceil(math.sqrt(n_steps)))


# --------------------------------------------------------------------------
# array / scalarized programs behind one custom_vmap
# --------------------------------------------------------------------------


#: How each program runs under ``vmap`` (see `_dual`), by batch size: ``(s, c)`` runs
#: the scalarized program for batches of ``s`` runs or more (the array program, vmapped,
#: below that) and cuts its fusion (`so3jax._scalarize.fusion_cut`, CPU only) from ``c``
#: runs on; ``None`` never. ``"scalar"`` and ``"array"`` are ``program="scalar"`` and
#: ``"array"`` (benchmarks); ``"jvp"``: the programs of second derivatives (`_dual_jvp`).
#: Each entry is where the scalarized program pays for its longer compile within the
#: calls a sweep or a `tune` makes, on a 2-core CPU with each loop one kernel; the
#: second derivatives' programs stay in the array layout below 32 runs, where they
#: compile faster and run as fast. Measured by ``benchmarks/layouts.py`` (tables in
#: ``docs/performance.md``).
BATCHED_LAYOUT = {
    "run": (16, 16),
    "scalar": (1, 64),
    "tangent": (16, 16),
    "jacobian": (16, 16),
    "adjoint": (None, None),
    "array": (None, None),
    "jvp": (32, 32),
}

#: On a GPU, the entries that differ from `BATCHED_LAYOUT` (the others are the CPU's).
#: A GPU is latency bound in either layout up to a few thousand runs, and there the
#: scalarized program compiles several times longer than the array program: each entry
#: scalarizes from where 100 calls with their compile take less time than the array
#: program's. ``"run"``: from 32768 runs; ``"jacobian"`` (``grad`` / ``jacfwd`` through a
#: few scalars): from 16384 runs, where a `tune` of 100 iterations (its default) breaks
#: even; ``"jvp"`` (second derivatives, `_dual_jvp`): from 4096 runs. Cuts are CPU only
#: (`so3jax._scalarize.cut_index`). Measured by ``benchmarks/layouts.py`` on the GPUs
#: named in ``benchmarks/results/layouts-*gpu*.json``.
GPU_LAYOUT = {"run": (32768, None), "jacobian": (16384, None), "jvp": (4096, None)}

#: `so3jax.sweep`'s runs per chunk when none is given, per device: ``"cpu"`` 1024 (a
#: 2-core CPU is throughput bound from a few hundred runs; larger chunks only cost
#: memory), ``"gpu"`` 65536 (latency bound: each chunk's steps take about the same
#: time at 1024 runs as at 65536; ``benchmarks/sweep.py``). A GPU chunk is cut below
#: 65536 where its saved points would fill more than half the device's memory
#: (`sweep_chunk`).
SWEEP_CHUNK = {"cpu": 1024, "gpu": 65536}


#: Whether `so3jax.sweep` steps its chunks as the scalarized program when the caller
#: leaves ``scalarize`` to it, per platform. CPU: yes (several times faster in batches).
#: GPU: no: the compiled sweep runs about as fast in either layout, and the array
#: program compiles several times faster, so it pays unless a process sweeps the same
#: program many times (``benchmarks/sweep.py`` with and without ``--array``).
SWEEP_SCALARIZE = {"cpu": True, "gpu": False}


#: XLA's options for the programs the library compiles itself (`so3jax.tune`'s iteration:
#: `jit_own`), per platform. CPU: LLVM's ``-O2`` instead of XLA's default ``-O3``, which
#: compiles the hoisted loops (`_hoisted`) faster and runs the scalarized programs of
#: small batches faster, at a small cost to the array layout below 16 runs; whole `tune`
#: calls are faster or level (``benchmarks/tune.py``).
#: A level the caller names in ``XLA_FLAGS`` wins (the test suite's 0).
OWN_COMPILER_OPTIONS = {"cpu": {"xla_backend_optimization_level": 2}}


def own_compiler_options() -> dict | None:
    """`OWN_COMPILER_OPTIONS` for the default backend, less what ``XLA_FLAGS`` sets; or ``None``."""
    flags = os.environ.get("XLA_FLAGS", "")
    options = OWN_COMPILER_OPTIONS.get(jax.default_backend(), {})
    options = {k: v for k, v in options.items() if f"--{k}=" not in flags}
    return options or None


def jit_own(fn: Callable) -> Callable:
    """``jax.jit(fn)`` for a program the library compiles itself, with `own_compiler_options`.

    Should XLA not know an option (a later jaxlib may drop one: JAX 0.11's rejects a CPU
    flag 0.10's knows), the program compiles with XLA's defaults instead, with a warning.
    """
    plain = jax.jit(fn)
    options = own_compiler_options()
    if options is None:
        return plain
    try:
        tuned = jax.jit(fn, compiler_options=options)
    except TypeError:  # pragma: no cover - a JAX whose `jit` takes no compiler options
        return plain
    rejected = []

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if not rejected:
            try:
                return tuned(*args, **kwargs)
            except Exception as e:  # XLA's error type moves between JAX versions
                if "compile option" not in str(e):
                    raise
                rejected.append(e)
                warnings.warn(
                    f"so3jax: XLA rejected the compile options {options} ({e}); "
                    "compiling with its defaults",
                    stacklevel=2,
                )
        return plain(*args, **kwargs)

    return call


def sweep_scalarize(devices) -> bool:
    """Whether `so3jax.sweep` over ``devices`` runs the scalarized program by default
    (`SWEEP_SCALARIZE`; a TPU counts as a GPU)."""
    return SWEEP_SCALARIZE["cpu" if list(devices)[0].platform == "cpu" else "gpu"]


def sweep_chunk(devices, n_saved: int, itemsize: int) -> int:
    """Default runs per chunk of `so3jax.sweep` over ``devices``.

    ``SWEEP_CHUNK`` of the devices' platform, per device; on an accelerator at most
    as many runs as keep ``n_saved`` saved points of every run (48 numbers each, of
    ``itemsize`` bytes) within half the smallest device's memory (16 GiB where a device
    does not say), and at least `SWEEP_CHUNK` ``["cpu"]``. The peak memory of a seed
    chunk is about 34 numbers a saved point; 48 leaves room for a quadrotor's state.
    """
    devices = list(devices)
    if devices[0].platform == "cpu":
        return SWEEP_CHUNK["cpu"] * len(devices)
    known = []  # a TPU counts as a GPU
    for d in devices:
        try:
            known.append((d.memory_stats() or {}).get("bytes_limit"))
        except Exception:  # a backend without memory statistics
            pass
    known = [x for x in known if x]
    budget = (min(known) if known else 16 * 2**30) // 2  # unknown: a 16 GiB device
    fits = budget // (n_saved * 48 * itemsize)
    return max(SWEEP_CHUNK["cpu"], min(SWEEP_CHUNK["gpu"], fits)) * len(devices)


#: On a CPU, a batch of these programs runs in tiles, one tile after the other
#: (`_in_tiles`), each of about this many values per scalar component: a tile of ``m``
#: runs of a Jacobian program with ``n`` columns holds ``m (1 + n)`` (the primal and its
#: tangents). A tangent column reads many materialized values per operation, and
#: a tile's stay in the core's cache where a whole batch's do not. Batches run in
#: ``round(runs / m)`` tiles for ``m`` the power of 2 nearest ``192 / (1 + n)``, each a
#: multiple of `TILE_MULTIPLE` runs (from 96 runs for the seed's two gains). The forward
#: pass gains nothing from tiles. Measured by ``benchmarks/layouts.py``.
BATCH_TILE = {"jacobian": 192}

#: Tiles only for runs that observe at most this many scalars per saved point (a cost's
#: integrand, not a whole trajectory): where the saved points and their columns dominate,
#: tiles do not pay and cost memory.
TILE_MAX_OBSERVED = 8

#: Tiles are a multiple of this many runs (a vector register's float64 lanes with
#: AVX-512): tiles of 52 and 86 runs were slower than 64.
TILE_MULTIPLE = 8


def batch_tiles(what: str, runs: int, columns: int = 0, observed: int = 1) -> tuple[int, int]:
    """``(n, size)``: a batch of ``runs`` runs of program ``what`` with ``columns``
    tangent columns, observing ``observed`` scalars per saved point, runs as ``n`` tiles
    of ``size`` runs (`BATCH_TILE`); ``(1, runs)`` untiled."""
    values = BATCH_TILE.get(what)
    if values is None or not _one_cpu_device() or observed > TILE_MAX_OBSERVED:
        return 1, runs
    scalar_from, _ = batched_layout(what)
    tile = 2 ** round(math.log2(values / (1 + columns)))
    n = round(runs / tile)
    if scalar_from is None or runs < scalar_from or n < 2:
        return 1, runs
    size = -(-runs // n)
    size = -(-size // TILE_MULTIPLE) * TILE_MULTIPLE
    if size < scalar_from:  # a tile runs the program a batch of its size would
        return 1, runs
    return -(-runs // size), size


def _one_cpu_device() -> bool:
    """Whether JAX runs on one CPU device: where the engine's CPU-only choices (hoisted
    loops, tiles) apply. A sharded program is XLA's to partition."""
    return jax.default_backend() == "cpu" and jax.device_count() == 1


def batched_layout(what: str) -> tuple:
    """``(s, c)`` for program ``what`` on the default backend (`BATCHED_LAYOUT`, `GPU_LAYOUT`)."""
    if jax.default_backend() == "gpu":
        return GPU_LAYOUT.get(what, BATCHED_LAYOUT[what])
    return BATCHED_LAYOUT[what]


def _dual(
    array_fn: Callable, scalar_fn: Callable, what: str, settle=None, columns=None
) -> Callable:
    """``array_fn`` when unbatched; ``vmap`` of ``scalar_fn`` when batched.

    ``settle``: how the derivative rule (`_dual_jvp`) starts the carry tangents of the
    programs' loops (``None``: as JAX finds them). ``columns``: for the ``jvp`` of a
    Jacobian program, where its columns are (`_columns_outside`).

    ``scalar_fn`` raises `ScalarizeError` at trace time for an unsupported
    primitive (a loop, dynamic indexing, `jax.checkpoint` inside the step); the
    batched call then vmaps ``array_fn``, silently: nobody asked for the
    scalarized program.

    ``array_fn`` is traced once per call: the ``custom_vmap`` and its batching
    rule both run that jaxpr (`_Traced`) instead of tracing ``array_fn`` again
    (through the derivative programs' ``jvp`` and column ``vmap``, a second trace
    cost more than batching the first one). Tracers it closes over are constants
    of the jaxpr, closed over as before.

    The call is a ``custom_jvp`` whose derivative JAX can differentiate, batch and
    transpose again (`_dual_jvp`: JAX's ``jvp`` of ``array_fn``, or of the program
    `_dual` would run under ``vmap`` behind a ``linear_call``), for two reasons:

    - **Second derivatives.** The engine's derivative rules run these programs on
      primals; ``jax.hessian`` (or ``jacfwd`` / ``jvp`` over ``grad``) then
      differentiates the rule's programs again. A ``custom_vmap`` differentiated
      inside another transform's ``vmap`` or partial evaluator returned tangents
      batched unlike their primals or unknown primals ("Custom JVP rule must
      produce primal and tangent outputs with corresponding shapes",
      "Linearization failed to produce known values").
    - **Bound whole under ``grad``.** When ``grad`` linearizes the engine's
      ``custom_jvp`` rule, JAX runs that rule under its partial evaluator, whose
      ``scan`` and ``cond`` rules partially evaluate a loop even when all its
      inputs are known. The programs the rule runs on primals have only known
      inputs, but under ``vmap`` their scalarized loop bodies were partially
      evaluated anyway, and their fusion cuts hoisted out of the loop (longer to
      lower and to compile). A ``custom_jvp`` call whose inputs are all known is
      bound whole (``JaxprTrace.process_custom_jvp_call``).
    """

    @jax.custom_jvp
    def call(*args):
        with _tracing(what):
            with _plan.deferred() as pending:  # kept only if no batch replaces this trace
                closed, shape = jax.make_jaxpr(array_fn, return_shape=True)(*args)
            traced = _Traced(closed, jax.tree.structure(shape))
            before = _plan.count()
            out = _dual_of(traced, scalar_fn, what, columns)(*args)
            if not _plan.noted_since(before, "layout"):
                _plan.extend(pending)
                _plan.note("layout", program=what, runs=1, layout="array")
            return out

    rule = functools.partial(_dual_jvp, array_fn, scalar_fn, what, settle)
    call.defjvp(rule, symbolic_zeros=True)
    return call


def _dual_jvp(array_fn: Callable, scalar_fn: Callable, what: str, settle, primals, tangents):
    """`_dual`'s derivative (second derivatives of a run: its rule's programs differentiated).

    For the forward, tangent and Jacobian programs, the value is a `_dual` of the same
    programs (scalarized under a ``vmap`` of 16 runs or more, `BATCHED_LAYOUT`) and the
    tangent a ``linear_call`` (`_linear_tangent`) whose program is the ``jvp`` of the
    program `_dual` would run, itself a `_dual` (``"jvp"``): a batch's second
    derivatives run the batch's program, not the array program's. Integer outputs (a
    run's status) get their ``float0`` zeros outside the ``linear_call``. The other
    programs, and the ``"jvp"`` programs themselves (third derivatives): JAX's ``jvp``
    of the array program (`_array_jvp`).

    The ``linear_call``'s batching rule (`so3jax._linear_call`) leaves a call with
    nothing batched unbatched: JAX calls it under every ``vmap`` in scope (the inner
    ``jacfwd``'s basis of ``jacfwd`` of ``jacfwd`` too), and batching its outputs there
    would batch this rule's value with its tangent.

    ``settle(primals, leaves, t_leaves, nz) -> (t_leaves, nz)`` (`_dual`'s, the Jacobian
    program's `_settle_jacobian_tangents`) starts the loop's carry tangents that a step
    makes nonzero with zeros, so that JAX differentiates and batches each loop of the
    ``jvp`` programs once (shorter to lower; the same run and compile times).
    """
    _plan.note("derivative", strategy="second derivative", program=what)
    if what not in ("run", "tangent", "jacobian") or not _HAVE_LINEAR_CALL_BATCHING:
        return _array_jvp(array_fn, primals, tangents)
    leaves, treedef = jax.tree.flatten(primals)
    t_leaves, real = _tangent_leaves(tangents)
    t_leaves, nz = (t_leaves, real) if settle is None else settle(primals, leaves, t_leaves, real)

    out = _front(_batched_with(_dual(array_fn, scalar_fn, what, settle)(*primals), primals))
    # Integer and boolean outputs (a run's status) have float0 tangents, outside the
    # linear_call.
    out_nz = [_is_float(o) for o in jax.tree.leaves(out)]
    plain = _float_tangent(array_fn, treedef, nz, out_nz)
    columns = None
    if what == "jacobian":  # its columns outside the runs in the jvp program too
        in_cols, out_cols = _jacobian_columns(primals, jax.tree.structure(out))
        # the jvp program's arguments are (xs, ts, others): the differentiated leaves,
        # their tangents (shaped alike), and every leaf
        xs_cols = _pick(nz, in_cols)
        columns = (xs_cols + xs_cols + in_cols, _pick(out_nz, out_cols))
    fast = _dual(plain, _float_tangent(scalar_fn, treedef, nz, out_nz), "jvp", columns=columns)
    xs, ts = _pick(nz, leaves), _pick(nz, t_leaves)
    # The tangents the settle added are zeros (not real ones): `_linear_tangent`'s transpose.
    tan = _linear_tangent(plain, fast, xs, leaves, ts, _pick(nz, real))
    return out, _with_float0(out, out_nz, tan)


def _float_tangent(fn: Callable, treedef, nz: list, out_nz: list) -> Callable:
    """``tangent(xs, ts, others, **kw)``: JAX's ``jvp`` of ``fn`` at the leaves
    ``others`` (``treedef``'s) with those flagged in ``nz`` set to ``xs`` and moved by
    ``ts``; the tangents of its outputs flagged in ``out_nz`` (the float ones). A
    ``batched`` keyword (a `custom_vmap` rule's flags of ``(xs, ts, others)``) reaches
    ``fn`` as its own arguments' flags."""

    def tangent(xs, ts, others, **kw):
        if kw.get("batched") is not None:
            xb, _, ob = kw["batched"]
            kw["batched"] = tuple(jax.tree.unflatten(treedef, _fill(nz, xb, ob)))

        def g(*xs):
            return fn(*jax.tree.unflatten(treedef, _fill(nz, xs, others)), **kw)

        return _pick(out_nz, jax.tree.leaves(jax.jvp(g, tuple(xs), tuple(ts))[1]))

    return tangent


def _with_float0(out, out_nz: list, tan: list):
    """The tangent tree of ``out``: ``tan`` for the leaves flagged in ``out_nz``, ``float0``
    zeros for the others (integer and boolean outputs)."""
    leaves = jax.tree.leaves(out)
    zeros = [
        None if k else np.zeros(jnp.shape(o), jax.dtypes.float0)
        for o, k in zip(leaves, out_nz, strict=True)
    ]
    return jax.tree.unflatten(jax.tree.structure(out), _fill(out_nz, tan, zeros))


def _linear_tangent(plain: Callable, fast: Callable, xs, others, ts, real: list, max_columns=None):
    """``fast(xs, ts, others)``, linear in ``ts``, transposable and differentiable.

    ``fast`` (a `_dual`: a ``custom_vmap`` that JAX can neither partially evaluate nor
    transpose) runs as the program of a ``linear_call``. Its transpose (``grad`` of
    ``grad``): through at most `FORWARD_JACOBIAN_MAX` scalars of the ``ts`` flagged
    ``real`` (the others are zeros that only settle loops), ``fast`` once per unit
    tangent, contracted with the cotangent (`_transpose_by_columns`); through more,
    JAX's transpose of ``plain`` (the same map on the array program). Behind a
    ``custom_jvp`` whose rule is JAX's ``jvp`` of ``plain``, because a ``linear_call``
    cannot differentiate its residuals: third derivatives. ``max_columns``: the
    largest number of columns (default `FORWARD_JACOBIAN_MAX`); `forward_differentiated`
    takes columns whatever their number.
    """
    shapes = [jax.ShapeDtypeStruct(jnp.shape(t), jnp.result_type(t)) for t in ts]
    n_real = sum(math.prod(s.shape) for s, r in zip(shapes, real, strict=True) if r)
    max_columns = FORWARD_JACOBIAN_MAX if max_columns is None else max_columns

    def callee(res, ts):
        return fast(res[0], ts, res[1])

    def transpose(res, cts):
        if 0 < n_real <= max_columns:
            return _transpose_by_columns(lambda ts: callee(res, ts), cts, shapes, real)
        zeros = [jnp.zeros(s.shape, s.dtype) for s in shapes]
        return jax.vjp(lambda ts: plain(res[0], ts, res[1]), zeros)[1](cts)[0]

    @jax.custom_jvp
    def tangent(xs, others, ts):
        return linear_call(callee, transpose, (xs, others), ts)

    def tangent_jvp(primals, tangents):
        return _array_jvp(lambda xs, others, ts: plain(xs, ts, others), primals, tangents)

    tangent.defjvp(tangent_jvp, symbolic_zeros=True)
    return tangent(xs, others, ts)


def forward_differentiated(fn: Callable) -> Callable:
    """``fn`` with JAX's ``jvp`` of it as its derivative, behind a ``linear_call`` whose
    transpose runs that ``jvp`` once per unit tangent (`_transpose_by_columns`).

    For programs JAX differentiates in forward mode only (a ``while_loop``: an adaptive
    run through `diffrax.ForwardMode`, whose one-pass Jacobian is such a program): reverse
    mode over their derivatives (``jacrev`` of ``jacfwd``, ``grad`` of a gradient's norm)
    then works, instead of raising JAX's "Reverse-mode differentiation does not work for
    lax.while_loop". Integer outputs get ``float0`` tangents.
    """

    @jax.custom_jvp
    def call(*args):
        return fn(*args)

    def rule(primals, tangents):
        leaves, treedef = jax.tree.flatten(primals)
        t_leaves, nonzero = _tangent_leaves(tangents)
        nz = [z and _is_float(x) for x, z in zip(leaves, nonzero, strict=True)]
        out = call(*primals)
        out_nz = [_is_float(o) for o in jax.tree.leaves(out)]
        plain = _float_tangent(fn, treedef, nz, out_nz)
        xs, ts = _pick(nz, leaves), _pick(nz, t_leaves)
        tan = _linear_tangent(plain, plain, xs, leaves, ts, [True] * len(ts), math.inf)
        return out, _with_float0(out, out_nz, tan)

    call.defjvp(rule, symbolic_zeros=True)
    return call


def _transpose_by_columns(linear: Callable, cts, shapes: list, real: list) -> list:
    """The transpose of ``linear`` (a linear map of arrays shaped as ``shapes``) at
    ``cts``, from one run of ``linear`` per unit input of the arrays flagged ``real``
    (under `jax.lax.map`: one program for all columns), each contracted with ``cts``.
    The arrays not flagged get zero cotangents: only zeros ever enter there.

    Reverse over reverse through a few gains (``jax.jacrev(jax.jacrev(cost))``) runs
    this way several times faster, and compiles faster, than JAX's transpose of the
    array program (`benchmarks/tune.py`'s Hessian rows).
    """
    zeros = [jnp.zeros(s.shape, s.dtype) for s in shapes]
    cols = _unit_columns(_pick(real, zeros))

    def column(col):
        out = linear(_fill(real, list(col), zeros))
        pairs = zip(jax.tree.leaves(cts), jax.tree.leaves(out), strict=True)
        terms = [jnp.sum(c * o) for c, o in pairs]
        return functools.reduce(jnp.add, terms)

    vals = jax.lax.map(column, cols)
    picked = _pick(real, shapes)
    parts = jnp.split(vals, np.cumsum([math.prod(s.shape) for s in picked])[:-1].tolist())
    cotangents = [p.reshape(s.shape).astype(s.dtype) for p, s in zip(parts, picked, strict=True)]
    return _fill(real, cotangents, zeros)


def _array_jvp(array_fn: Callable, primals, tangents):
    """JAX's ``jvp`` of ``array_fn`` through the nonzero tangents, its outputs batched as
    `_dual`'s batching rule batches them: every output, batch axis first.

    JAX batches a ``custom_jvp`` call's function and its rule apart, and a jitted
    batch (``vmap`` of `so3jax.rollout_cost`, say) fixes each output's batch axis
    from the function's. `_dual`'s ``custom_vmap`` batches every output on axis 0;
    JAX's ``vmap`` of a ``scan`` stacks on axis 0 and batches on axis 1, and leaves
    unbatched what no batched input moves. Without `_batched_with` and `_front`,
    ``jax.hessian`` of the mean cost over a batch of starts raised "Cannot
    concatenate arrays with shapes that differ in dimensions other than the one
    being concatenated".
    """
    leaves, treedef = jax.tree.flatten(primals)
    t_leaves, nz = _tangent_leaves(tangents)
    out, tan = _jvp_through(array_fn, treedef, leaves, t_leaves, nz)
    return _front(_batched_with(out, primals)), tan


def _jvp_through(fn: Callable, treedef, leaves: list, t_leaves: list, nz: list):
    """JAX's ``jvp`` of ``fn(*unflatten(leaves))`` through the leaves flagged in ``nz``
    alone (the others enter as constants: no tangent term where they are used)."""

    def g(*xs):
        return fn(*jax.tree.unflatten(treedef, _fill(nz, xs, leaves)))

    return jax.jvp(g, tuple(_pick(nz, leaves)), tuple(_pick(nz, t_leaves)))


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


class _Traced:
    """A traced array program: called as it was traced, or batched with its loops settled.

    Under ``vmap``, a `lax.scan` whose carry starts partly unbatched finds which
    components become batched by batching its body again until nothing changes:
    two passes over the forward loop's body for the seed (the run's status
    starts unbatched), two over the Jacobian program's (its tangents start as
    unbatched zeros), each nested scan once more per pass. `vmap` walks
    the jaxpr's top-level equations and, before each loop, batches the carry
    components that its body would batch (`sc.carry_fixed_point`: the same
    fixed point, on flags), so that JAX batches each body once. What stays unbatched
    (the reference attitude a batch shares) stays so. The scalarized programs do
    the same on their flat components (`sc.settle_batched`, the same fixed point).
    """

    def __init__(self, closed, out_tree):
        self.closed, self.out_tree = closed, out_tree

    def __call__(self, *args):
        return self._eval(jax.tree.leaves(args), None, None)

    def vmap(self, axis_size: int, in_batched, args):
        """``vmap`` of the program over ``args`` (batched per ``in_batched``, on axis 0)."""
        axes = tuple(jax.tree.map(lambda b: 0 if b else None, ib) for ib in in_batched)
        flags = [bool(b) for b in jax.tree.leaves(in_batched)]

        def one_run(one, *a):
            return self._eval(jax.tree.leaves(a), flags, one)

        one = jnp.zeros((axis_size,), jnp.int32)  # (the caller, `_dual_of`, sets `_tracing`)
        return jax.vmap(one_run, in_axes=(0, *axes))(one, *args)

    def _eval(self, leaves: list, flags: list | None, one):
        jaxpr = self.closed.jaxpr
        env = dict(zip(jaxpr.constvars, self.closed.consts, strict=True))
        env.update(zip(jaxpr.invars, leaves, strict=True))
        batched = dict.fromkeys(jaxpr.constvars, False)
        batched.update(zip(jaxpr.invars, flags or [False] * len(leaves), strict=True))

        def read(v):
            return v.val if isinstance(v, jex_core.Literal) else env[v]

        def is_batched(v):
            return isinstance(v, jex_core.Var) and batched[v]

        for e in jaxpr.eqns:
            ins = [read(v) for v in e.invars]
            bs = [is_batched(v) for v in e.invars]
            split = sc.scan_split(e) if flags is not None and e.primitive.name == "scan" else None
            if split is not None:
                nc, ncar = split
                settled = sc.carry_fixed_point(e.params["jaxpr"].jaxpr, bs, nc, ncar)
                for i, (now, then) in enumerate(zip(bs[nc : nc + ncar], settled, strict=True)):
                    if then and not now:
                        ins[nc + i], bs[nc + i] = _batch_by(ins[nc + i], one), True
            params = e.primitive.get_bind_params(e.params)
            with e.ctx.manager:
                if e.primitive.name == "scan":
                    outs = _hoisted(functools.partial(e.primitive.bind, **params), *ins)
                else:
                    outs = e.primitive.bind(*ins, **params)
            outs = outs if e.primitive.multiple_results else [outs]
            env.update(zip(e.outvars, outs, strict=True))
            batched.update(zip(e.outvars, sc.eqn_batched(e, bs), strict=True))
        return jax.tree.unflatten(self.out_tree, [read(v) for v in jaxpr.outvars])


def _batch_by(x, one):
    """``x`` made batched by adding ``one``, a batched zero (values unchanged)."""
    x = jnp.asarray(x)
    if x.dtype == jnp.bool_:
        return jnp.logical_or(x, one != 0)
    if jnp.issubdtype(x.dtype, jnp.number):
        return x + one.astype(x.dtype)
    return x  # (a key, say: JAX's own fixed point batches it if it must)


def _dual_of(array_fn: "_Traced", scalar_fn: Callable, what: str, columns=None) -> Callable:
    fn = custom_vmap(array_fn)

    @fn.def_vmap
    def _rule(axis_size, in_batched, *args):
        columns, observed = 0, 1
        if what == "jacobian":
            columns = _column_count(args, in_batched, array_fn.out_tree)
            ys = array_fn.closed.out_avals[: array_fn.out_tree.children()[0].num_leaves]
            observed = sum(math.prod(y.shape[1:]) for y in ys)
        n, size = batch_tiles(what, axis_size, columns, observed)
        if n > 1:
            _plan.note("tiles", program=what, runs=axis_size, n=n, size=size)
            return _in_tiles(_traced_rule, axis_size, n, size, in_batched, args)
        return _traced_rule(axis_size, in_batched, *args)

    def _traced_rule(axis_size, in_batched, *args):
        with _tracing(what, axis_size):
            return _batched_rule(axis_size, in_batched, *args)

    def _batched_rule(axis_size, in_batched, *args):
        axes = tuple(jax.tree.map(lambda b: 0 if b else None, ib) for ib in in_batched)
        scalar_from, cut_from = batched_layout(what)
        if scalar_from is None or axis_size < scalar_from:
            _plan.note(
                "layout",
                program=what,
                runs=axis_size,
                layout="array",
                why=f"fewer runs than the scalarized layout's threshold {scalar_from}",
            )
            out = array_fn.vmap(axis_size, in_batched, args)
            return out, jax.tree.map(lambda _: True, out)
        try:
            cuts = cut_from is not None and axis_size >= cut_from
            index = sc.cut_index(args) if cuts else None

            def runs(*args):
                if what in ("run", "scalar", "tangent", "jacobian", "jvp") and index is not None:
                    # The forward, tangent and Jacobian loops settle their carry's batching
                    # up front (`sc.settle_batched`); the adjoint's backward scan does not.
                    def cut(one, *a):
                        return scalar_fn(*a, cut=index, batched=in_batched, one=one)

                    one = jnp.zeros((axis_size,), jnp.int32)
                    return jax.vmap(cut, in_axes=(0, *axes))(one, *args)
                return jax.vmap(functools.partial(scalar_fn, cut=index), in_axes=axes)(*args)

            cols = _jacobian_columns(args, array_fn.out_tree) if what == "jacobian" else columns
            out = runs(*args) if cols is None else _columns_outside(runs, args, in_batched, *cols)
            _plan.note("layout", program=what, runs=axis_size, layout="scalarized", cuts=cuts)
        except sc.ScalarizeError as e:
            _plan.note(
                "layout",
                program=what,
                runs=axis_size,
                layout="array",
                why=f"the step cannot be scalarized: {e}",
            )
            out = array_fn.vmap(axis_size, in_batched, args)
        return out, jax.tree.map(lambda _: True, out)

    return fn


def _in_tiles(rule: Callable, axis_size: int, n: int, size: int, in_batched, args):
    """``rule(axis_size, in_batched, *args)`` (a `custom_vmap` rule) run as ``n``
    tiles of ``size`` runs under `lax.map`, one after the other (`BATCH_TILE`).

    The batch is padded to ``n * size`` runs with copies of its last run, whose
    results are dropped.
    """
    pad = n * size - axis_size
    leaves, treedef = jax.tree.flatten(args)
    flags = [bool(b) for b in jax.tree.leaves(in_batched)]

    def tiles(x):  # (B, ...) -> (n, size, ...)
        if pad:
            x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)])
        return x.reshape((n, size) + x.shape[1:])

    def one(tile):
        it = iter(tile)
        tile_args = jax.tree.unflatten(
            treedef, [next(it) if b else x for x, b in zip(leaves, flags, strict=True)]
        )
        return rule(size, in_batched, *tile_args)[0]

    outs = jax.lax.map(one, [tiles(x) for x, b in zip(leaves, flags, strict=True) if b])
    out = jax.tree.map(lambda y: y.reshape((n * size,) + y.shape[2:])[:axis_size], outs)
    return out, jax.tree.map(lambda _: True, out)


def _columns_outside(runs: Callable, args, in_batched, in_cols: list, out_cols: list):
    """``runs(*args)`` (a batch of scalarized Jacobian programs, or their ``jvp``) with
    the column axis of the Jacobian's tangents outside the runs' axis.

    ``in_cols`` gives, per leaf of ``args``, the axis of the columns in one run's
    leaf (``None``: the leaf has none); ``out_cols`` the same per leaf of the output.

    Under ``runs`` alone the Jacobian program's columns are a ``vmap`` inside the
    runs' ``vmap``, so every tangent component is a ``(B, n)`` array whose columns
    are its minor axis: each operation between a primal ``(B,)`` and a tangent
    broadcasts the primal across that axis of 2 (two gains), an inner loop XLA's CPU
    code does not vectorise well. Here one column at a time runs under ``runs``, and
    the columns are a ``vmap`` around it: tangent components are ``(n, B)``, the
    primal stays ``(B,)`` and is computed once (it does not depend on the tangents).
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


def _column_count(args, in_batched, out_tree) -> int:
    """The number of tangent columns of a batched call of the Jacobian program."""
    in_cols, _ = _jacobian_columns(args, out_tree)
    pairs = zip(jax.tree.leaves(args), jax.tree.leaves(in_batched), in_cols, strict=True)
    return next((jnp.shape(x)[c + int(b)] for x, b, c in pairs if c is not None), 0)


def _jacobian_columns(args, out_tree) -> tuple[list, list]:
    """`_columns_outside`'s ``in_cols`` and ``out_cols`` for the Jacobian program:
    ``(P, c0, dP, dc) -> (ys, cN, dys, dcN)``, one run's columns on axis 0 of ``dP`` and
    ``dc``, axis 1 of ``dys`` (after the saved points) and axis 0 of ``dcN``."""
    n_in = [len(jax.tree.leaves(a)) for a in args]
    n_out = [t.num_leaves for t in out_tree.children()]
    in_cols = [None] * (n_in[0] + n_in[1]) + [0] * (n_in[2] + n_in[3])
    out_cols = [None] * (n_out[0] + n_out[1]) + [1] * n_out[2] + [0] * n_out[3]
    return in_cols, out_cols


def _component_flags(example, batched) -> list:
    """Per scalar component of ``example`` (in `sc.split` order), its leaf's flag in ``batched``.

    ``batched`` holds one flag per leaf of ``example`` (a `custom_vmap` rule's
    ``in_batched`` for the same arguments).
    """
    return [
        b
        for leaf, b in zip(jax.tree.leaves(example), jax.tree.leaves(batched), strict=True)
        for _ in range(math.prod(jnp.shape(leaf)))
    ]


#: Steps per iteration of the step loops' `lax.scan` (its ``unroll``), read at trace time.
#: 1 everywhere for now; `benchmarks/unroll.py` measures other values per backend.
SCAN_UNROLL = 1

#: The jaxlib releases (major, minor) on which the whole test suite passes with the
#: loops hoisted (`HOIST_LOOPS`): 0.10, 0.11 and 0.12. On another, hoisting stays off
#: unless asked for: XLA's older emitter aborts the process, not raises, where it
#: cannot compile a hoisted loop.
HOIST_VERIFIED = _jax.TESTED


def hoisting_verified() -> bool:
    """Whether the installed jaxlib is one of `HOIST_VERIFIED`."""
    try:
        import jaxlib

        release = tuple(int(x) for x in jaxlib.__version__.split(".")[:2])
    except (ImportError, AttributeError, ValueError):
        return False
    return release in HOIST_VERIFIED


def _hoist_default() -> bool:
    """`HOIST_LOOPS`'s value at import: ``SO3JAX_HOIST_LOOPS`` (``0`` or ``1``) if set,
    else `hoisting_verified`."""
    asked = os.environ.get("SO3JAX_HOIST_LOOPS")
    return hoisting_verified() if asked is None else asked != "0"


#: Run the engine's loops as one kernel each on a CPU (`_hoisted`). ``False`` gives
#: XLA's default: one kernel per fusion, handed between the threads of its pool,
#: several times slower (``benchmarks/emitters.py``). On by default only on a jaxlib of
#: `HOIST_VERIFIED`. The environment variable ``SO3JAX_HOIST_LOOPS`` (read at import)
#: overrides that: ``0`` should XLA's older emitter refuse a loop of some scene (a
#: compile error naming a fusion kind, or an abort), ``1`` to try hoisting on another
#: jaxlib.
HOIST_LOOPS = _hoist_default()

#: The largest input leaf of a hoisted loop, in bytes, over the runs of a batch: one
#: kernel gives up XLA's threads, which pay for large batches: past 64 kB a leaf the
#: hoisted loop is slower than XLA's threaded one (``benchmarks/emitters.py``).
#: Under nested ``vmap`` (gains x attitudes by hand) only the innermost batch that
#: reaches the engine's batching rule counts: `so3jax.sweep` runs one flat batch per chunk.
HOIST_MAX_BYTES = 64 * 1024

#: What is being traced, innermost last (`_tracing`): the runs in its batch (a vmapped
#: program sees one run's shapes), whether its loops may be hoisted, and whether loops
#: with reductions may.
_TRACING = [(1, True, True)]


@contextlib.contextmanager
def _tracing(what: str, runs: int = 1):
    """Trace program ``what`` (a `_dual`'s) in a batch of ``runs`` runs.

    - Nothing is hoisted inside the ``"jvp"`` programs of second derivatives
      (`_dual_jvp`), nor in what they trace: hoisted, ``jax.hessian`` runs faster but
      compiles more than twice as long, which a second derivative rarely repays.
    - Only forward runs hoist loops with reductions; a derivative program's are written
      out first (`_unrolled`). A derivative program's loop can be batched again after
      `_hoisted` chose, by a ``vmap`` around a derivative JAX staged (no Python of ours
      runs then), and its reductions would then grow past `HOIST_MAX_REDUCED`:
      ``vmap`` of ``grad`` over 5 gain sets of the mean cost over 16 starts failed to
      compile so ("Fusion kind not implemented on CPU"). A forward run is batched
      through its own ``custom_vmap`` rule, which sizes it again.
    """
    n, hoist, _ = _TRACING[-1]
    _TRACING.append((n * int(runs), hoist and what != "jvp", what in ("run", "scalar", "array")))
    try:
        yield
    finally:
        _TRACING.pop()


#: Primitives a hoisted loop may hold. XLA compiles the loop with its older CPU
#: emitter, which refuses dots, convolutions, scatters and custom calls (linear
#: algebra, callbacks, sorting, FFTs): a loop with anything not listed runs as before.
_HOISTABLE = frozenset(
    """abs acos acosh add add_any and asin asinh atan atan2 atanh broadcast_in_dim cbrt ceil
    checkpoint clamp closed_call concatenate cond convert_element_type copy copy_p cos
    cosh custom_jvp_call custom_vjp_call custom_vjp_call_jaxpr custom_vmap_call div
    dynamic_slice dynamic_update_slice eq erf erf_inv erfc exp exp2 expm1 expand_dims floor
    ge gt integer_pow iota is_finite jit le log log1p logistic lt max min mul ne neg
    nextafter not optimization_barrier or pjit pow reduce_and reduce_max reduce_min
    reduce_or reduce_precision reduce_prod reduce_sum rem remat2 reshape rev round rsqrt scan
    select_n sign sin sinh slice sqrt square squeeze stack stop_gradient sub tan tanh
    transpose unstack while xor""".split()
)


#: The most elements a reduction in a hoisted loop may read, over the batch. Past 1024,
#: XLA fuses a reduction into a kind of kernel its older emitter does not implement
#: ("Fusion kind not implemented on CPU"): the array program's 3x3 products, sums over
#: ``(B, 3, 3, 3)`` arrays, compile hoisted for 37 runs and fail for 38.
HOIST_MAX_REDUCED = 1024


#: The reductions a hoisted loop may hold (all of `_HOISTABLE`'s), with the operation of
#: each step when `_unrolled` writes them out term by term.
_UNROLLED = {
    "reduce_sum": jax.lax.add,
    "reduce_prod": jax.lax.mul,
    "reduce_max": jax.lax.max,
    "reduce_min": jax.lax.min,
    "reduce_and": jax.lax.bitwise_and,
    "reduce_or": jax.lax.bitwise_or,
}


def _hoistable(jaxpr, runs: int = 1, reductions: bool = True) -> bool:
    """Whether every equation of ``jaxpr`` (nested ones too) is in `_HOISTABLE`, with no
    reduction (none at all without ``reductions``) over more than `HOIST_MAX_REDUCED`
    elements in a batch of ``runs`` runs (``runs=0``: whatever its reductions)."""
    for e in jaxpr.eqns:
        if e.primitive.name not in _HOISTABLE:
            return False
        if e.primitive.name in _UNROLLED:
            if not reductions or math.prod(e.invars[0].aval.shape) * runs > HOIST_MAX_REDUCED:
                return False
        if not all(_hoistable(j, runs, reductions) for j in sc.subjaxprs(e.params)):
            return False
    return True


#: The most terms a run that `_unrolled` writes a reduction out with: the 3-term sums
#: of the array layout's 3x3 products, the 9-term sums of a Frobenius product.
UNROLL_MAX_TERMS = 27


def _small_reduction(e) -> bool:
    if e.primitive.name not in _UNROLLED:
        return False
    shape = e.invars[0].aval.shape
    return (
        0 < math.prod(shape) and math.prod(shape[a] for a in e.params["axes"]) <= UNROLL_MAX_TERMS
    )


#: What `_has_small_reduction` and `_unrolled` found for a jaxpr (by identity, while it
#: lives). A step's jitted parts appear in a loop once per stage, and each level of
#: nesting asked again about the jaxprs below it: the seed's gradient over 16 runs
#: asked 98 times about 29 jaxprs and unrolled 28 of them 77 times.
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
    """``closed`` (a `ClosedJaxpr`) with its reductions over at most `UNROLL_MAX_TERMS`
    terms, nested jaxprs' too, written out term by term (`_eval_unrolled`).

    A batched loop's reductions grow with its batch, and XLA fuses a reduction over
    more than `HOIST_MAX_REDUCED` elements into a kernel its older emitter does not
    implement. Written out, the loop holds none, whatever batch a later ``vmap``
    gives it: so the derivative programs of the array layout can be hoisted, which
    makes them several times faster. A forward program keeps its reductions while
    they fit `HOIST_MAX_REDUCED` (written out, they are slower there); past it they are
    written out too, which is still faster than not hoisting.
    """
    if not _has_small_reduction(closed.jaxpr):
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


#: Elementwise primitives through which `_eval_unrolled` takes a term of a reduction
#: back to their operands (an operand of size 1 on the term's axis is broadcast).
_TERMWISE = frozenset(
    """abs add add_any atan2 convert_element_type cos cosh div exp expm1 integer_pow
    log log1p max min mul neg rsqrt select_n sign sin sinh sqrt square sub tan tanh""".split()
)


def _eval_unrolled(jaxpr, consts, args) -> list:
    """Evaluate ``jaxpr`` with its reductions over at most `UNROLL_MAX_TERMS` terms
    written out, term by term in row-major order.

    A term (``x`` at one index of the reduced axes) is computed from ``x``'s producer
    where only the reduction reads ``x`` and the producer is elementwise
    (`_TERMWISE`) or a broadcast, else sliced from ``x``: ``sum(A[:, :, None] *
    B[None], 1)`` becomes ``A[:, 0, None] * B[None, 0] + A[:, 1, None] * B[None, 1] +
    ...``. Sliced after the product instead, XLA computes the product once in full,
    which is slower.
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


def _hoisted(loop: Callable, *args):
    """``loop(*args)`` (a `lax.scan`), compiled as one kernel on a CPU.

    XLA's CPU runtime runs a loop body as one kernel per fusion: some 300 a step
    for the seed's batched forward pass, 640 for its Jacobian program, each
    dispatched on its own and handed between the threads of XLA's pool. A call
    tagged ``xla_cpu_small_call`` (and kept from inlining) is compiled whole into
    one function by XLA's older CPU emitter, as XLA's own small-loop pass does
    for loops under 1 kB (``xla_cpu_small_while_loop_byte_threshold``, a process
    flag). That makes the seed's forward pass about three times faster, for a batch
    and for a single run (``benchmarks/emitters.py``).

    The loop's inputs pass an `optimization_barrier` first: XLA otherwise sinks
    constant operands (a batch of starts closed over as a constant) into the call,
    and the older emitter aborts on constants of more than about 10 kB. The call
    also returns its inputs (unused): so they stay live to its end, and XLA cannot
    hand an input's memory to a value inside the loop. On JAX 0.11 and 0.12 it did
    (a loop's carry in an input's place, at the same offset, larger), and the older
    emitter then aborted the process (``Check failed:
    slice_to_buffer_table_index_.empty() || has_explicit_index``; the gradient of a
    free body's run whose start was a constant of the jitted cost). A loop that
    holds reductions where `_tracing` allows none (a derivative program's), or one
    over more than `HOIST_MAX_REDUCED` elements, is hoisted with its reductions written
    out (`_unrolled`) if that is all that stood in the way. Loops with a primitive
    outside `_HOISTABLE` or a reduction over more than `UNROLL_MAX_TERMS` terms and
    `HOIST_MAX_REDUCED` elements, loops whose largest input leaf takes more than
    `HOIST_MAX_BYTES` over the batch, second derivatives' loops (`_tracing`), every
    loop off a CPU, and every loop
    where JAX sees more than one device run as before: XLA partitions a sharded program after
    this choice, and a hoisted loop then calls collectives the older emitter cannot
    link (``__xla_cpu_runtime_AllReduce``, ``__xla_cpu_runtime_PartitionId``).
    """
    runs, hoist, reductions = _TRACING[-1]
    if _jax.set_xla_metadata is None or not HOIST_LOOPS or not hoist:
        why = "off (HOIST_LOOPS)" if hoist else "a second derivative's loop"
        _plan.note("hoisting", hoisted=False, runs=runs, why=why)
        return loop(*args)
    if not _one_cpu_device():
        _plan.note("hoisting", hoisted=False, runs=runs, why="not a single CPU device")
        return loop(*args)
    leaves = jax.tree.leaves(args)
    per_run = max((jnp.size(x) * jnp.result_type(x).itemsize for x in leaves), default=0)
    if per_run * runs > HOIST_MAX_BYTES:
        _plan.note("hoisting", hoisted=False, runs=runs, why="a leaf over HOIST_MAX_BYTES")
        return loop(*args)
    closed, shape = jax.make_jaxpr(loop, return_shape=True)(*args)
    hoisted = closed
    if not _hoistable(closed.jaxpr, runs, reductions) and _hoistable(closed.jaxpr, 0):
        hoisted = _unrolled(closed)  # only reductions stand in the way: write them out
    if not _hoistable(hoisted.jaxpr, runs, reductions):  # run the traced loop, not again
        _plan.note(
            "hoisting",
            hoisted=False,
            runs=runs,
            why="a primitive or reduction XLA's older emitter refuses",
        )
        outs = jex_core.jaxpr_as_fun(closed)(*leaves)
        return jax.tree.unflatten(jax.tree.structure(shape), outs)
    _plan.note("hoisting", hoisted=True, runs=runs, unrolled=hoisted is not closed)
    consts, leaves = jax.lax.optimization_barrier((list(hoisted.consts), leaves))

    @jax.jit
    def call(consts, leaves):
        outs = jex_core.jaxpr_as_fun(jex_core.ClosedJaxpr(hoisted.jaxpr, consts))(*leaves)
        return outs, (consts, leaves)

    with _jax.set_xla_metadata(xla_cpu_small_call="true", inlineable="false"):
        outs, _ = call(consts, leaves)
    return jax.tree.unflatten(jax.tree.structure(shape), outs)


#: The scalarized Jacobian program cuts the values its tangent columns consume
#: (`so3jax._scalarize.COLUMN_CUT_CONE`) in batches of this many runs or more (a tile's).
#: Below that the cuts cost more than they save; from it on they are faster, for a
#: little more compile time.
COLUMN_CUTS_FROM = 32


class _Loop:
    """The programs of one fixed-step loop (forward, tangent, adjoint), both layouts."""

    def __init__(self, step, observe, n_steps: int, save_every: int, K: int):
        self.step, self.observe = step, observe
        self.n, self.save_every, self.n_save = n_steps, save_every, n_steps // save_every
        self.K = min(K, n_steps)
        self.S = -(-n_steps // self.K)

    def _repeat(self, fn, x):
        """``save_every`` applications of ``fn`` under ``lax.scan``."""
        return jax.lax.scan(
            lambda x, _: (fn(x), None), x, None, length=self.save_every, unroll=SCAN_UNROLL
        )[0]

    def _save_loop(self, body, observe, x0):
        """``n_save`` blocks of ``save_every`` applications of ``body``, observed after each."""

        def block(x, _):
            x = body(x) if self.save_every == 1 else self._repeat(body, x)
            return x, observe(x)

        unroll = SCAN_UNROLL if self.save_every == 1 else 1
        return jax.lax.scan(block, x0, None, length=self.n_save, unroll=unroll)

    # ---------------- forward ----------------

    def fwd_array(self, P, c0):
        cN, ys = self._save_loop(lambda c: self.step(P, c), lambda c: self.observe(P, c), c0)
        return ys, cN

    def fwd_checkpointed(self, P, c0):
        """The array program with checkpointed segments: what plain autodiff differentiates.

        Save blocks are grouped into segments of about ``K`` steps, each under
        `jax.checkpoint`, so reverse mode stores one carry per segment and
        recomputes a segment's residuals when it transposes it: memory
        ``~ n / K + K`` steps instead of ``n``. The last segment is padded
        with blocks that leave the carry alone.
        """
        step, obs = self.step, self.observe
        m = _segment_blocks(self.n_save, max(1, round(self.K / self.save_every)))
        S = -(-self.n_save // m)
        padded = S * m != self.n_save

        def block(c, i):
            c1 = step(P, c) if self.save_every == 1 else self._repeat(lambda c: step(P, c), c)
            o = obs(P, c1)
            if padded:
                c1 = jax.tree.map(lambda a, b: jnp.where(i < self.n_save, a, b), c1, c)
            return c1, o

        @functools.partial(jax.checkpoint, prevent_cse=False)
        def segment(c, s):
            return jax.lax.scan(block, c, s * m + jnp.arange(m))

        cN, ys = jax.lax.scan(segment, c0, jnp.arange(S))
        ys = jax.tree.map(lambda a: a.reshape((S * m,) + a.shape[2:])[: self.n_save], ys)
        return ys, cN

    def fwd_scalar(self, P, c0, cut=None, batched=None, one=None):
        ex = (P, c0)
        body, _ = sc.flat_program(lambda pc: (pc[0], self.step(*pc)), ex, cut)
        obs, obs_struct = sc.flat_program(lambda pc: self.observe(*pc), ex, cut)
        flat = sc.split(ex)
        if batched is not None:
            flat = sc.settle_batched(body, flat, _component_flags(ex, batched), one)
        flat, ys = _hoisted(functools.partial(self._save_loop, body, obs), flat)
        _, cN = sc.join(flat, jax.eval_shape(lambda: ex))
        return sc.join(ys, obs_struct, (self.n_save,)), cN

    # ---------------- tangent (forward mode) ----------------
    #
    # The tangent programs carry tangents for the masked float leaves only: ``mP``
    # flags the parameters being differentiated, ``mc`` the carry leaves whose
    # tangent can be nonzero (`_tangent_masks`). Every other leaf is held at its
    # primal value, so no operation pays for a tangent that is known to be zero.

    @staticmethod
    def _masked(fn, mP, mc, P, c):
        """``(g, Pm, cm)``: ``fn(P, c)`` as ``g(Pm, cm)``, a function of the float leaves of
        ``P`` and ``c`` flagged in ``mP`` and ``mc`` (the others held at ``P`` and ``c``),
        and those leaves."""
        pf, cf = _floats(P), _floats(c)

        def g(Pm, cm):
            return fn(_with_floats(P, _fill(mP, Pm, pf)), _with_floats(c, _fill(mc, cm, cf)))

        return g, _pick(mP, pf), _pick(mc, cf)

    def _tstep(self, mP, mc, x):
        P, c, dP, dc = x

        def step(P, c):
            c1 = self.step(P, c)
            return _pick(mc, _floats(c1)), c1

        g, Pm, cm = self._masked(step, mP, mc, P, c)
        fr = _frame_flags(mc)
        if any(fr):
            dc1, c1 = _frame_step(g, Pm, cm, dP, dc, fr)
            return P, c1, dP, dc1
        _, dc1, c1 = jax.jvp(g, (Pm, cm), (list(dP), list(dc)), has_aux=True)
        return P, c1, dP, dc1

    def _tobs(self, mP, mc, x):
        P, c, dP, dc = x
        o, Pm, cm = self._masked(self.observe, mP, mc, P, c)
        fr = _frame_flags(mc)
        if any(fr):
            return _frame_observe(o, Pm, cm, dP, dc, fr)
        return jax.jvp(o, (Pm, cm), (list(dP), list(dc)))[1]

    def _obs_tangents(self, mP, mc, x) -> tuple[list, list]:
        """The observations after a state and their tangents as `frame_jvp` gives them
        (``None``, an array or a `Frame`), as flat lists."""
        P, c, dP, dc = x
        o, Pm, cm = self._masked(self.observe, mP, mc, P, c)
        outs, touts, _ = _jvp_with_frames(o, Pm, cm, dP, dc, _frame_flags(mc))
        return outs, touts

    def obs_kinds(self, mP, mc, P, c0, elements: list) -> tuple:
        """Per observation leaf, its kind in the Jacobian programs (`OBS_ZERO`, ...): how
        its tangent comes out of `frame_jvp` with the tangents ``mP``, ``mc`` (``mc``'s
        `FRAME` leaves as frames), traced once, abstractly. `OBS_ZERO` too where no
        element of it depends on the elements flagged in ``elements`` (per leaf of
        ``(P, c0)``, `_tangent_masks`): the reference attitude observed from a carry
        leaf that stacks it with the body's."""
        pl, pt = jax.tree.flatten(P)
        cl, ct = jax.tree.flatten(c0)

        def obs(*leaves):
            P_, c_ = (
                jax.tree.unflatten(pt, leaves[: len(pl)]),
                jax.tree.unflatten(ct, leaves[len(pl) :]),
            )
            return jax.tree.leaves(self.observe(P_, c_))

        hit = [bool(m.any()) for m in _mask_eval(_abstract_jaxpr(obs, pl + cl), elements)]
        pf, cf = _floats(P), _floats(c0)
        fr = _frame_flags(mc)
        kinds = []

        def spec(x, frame=False):
            shape = jnp.shape(x)[:-2] + (3,) if frame else jnp.shape(x)
            return jax.ShapeDtypeStruct(shape, jnp.result_type(x))

        def probe(dP, dc):
            outs, touts = self._obs_tangents(mP, mc, (P, c0, dP, dc))
            kinds[:] = [_obs_kind(o, t) for o, t in zip(outs, touts, strict=True)]
            return 0

        dP = [spec(x) for x in _pick(mP, pf)]
        dc = [spec(x, f) for x, f in zip(_pick(mc, cf), fr, strict=True)]
        jax.make_jaxpr(probe)(dP, dc)
        return tuple(k if h else OBS_ZERO for k, h in zip(kinds, hit, strict=True))

    def _jac_tobs(self, mP, mc, mo, x) -> list:
        """The Jacobian programs' observation tangents of one column: the leaves whose
        kind in ``mo`` is not `OBS_ZERO`, each as its kind stores it (`_obs_tangent`)."""
        outs, touts = self._obs_tangents(mP, mc, x)
        return [
            _obs_tangent(o, t, k) for o, t, k in zip(outs, touts, mo, strict=True) if k != OBS_ZERO
        ]

    def tan_array(self, mP, mc, P, c0, dP, dc0):
        step = functools.partial(self._tstep, mP, mc)
        x, dys = self._save_loop(step, functools.partial(self._tobs, mP, mc), (P, c0, dP, dc0))
        return dys, x[3]

    def tan_scalar(self, mP, mc, P, c0, dP, dc0, cut=None, batched=None, one=None):
        ex = (P, c0, dP, dc0)
        body, _ = sc.flat_program(functools.partial(self._tstep, mP, mc), ex, cut)
        tobs, tobs_struct = sc.flat_program(functools.partial(self._tobs, mP, mc), ex, cut)
        flat = sc.split(ex)
        if batched is not None:
            flat = sc.settle_batched(body, flat, _component_flags(ex, batched), one)
        flat, dys = _hoisted(functools.partial(self._save_loop, body, tobs), flat)
        x = sc.join(flat, jax.eval_shape(lambda: ex))
        return sc.join(dys, tobs_struct, (self.n_save,)), x[3]

    # ---------------- Jacobian (a few inputs: primal and columns in one pass) ----------------

    def jac_array(self, mP, mc, mo, P, c0, dP, dc0):
        """The run and its Jacobian's columns in one pass, array layout.

        ``dP``, ``dc0`` are the masked tangents with a leading axis of ``n``
        columns; the primal is computed once and the ``n`` tangents are batched
        over it. Returns ``(ys, cN, dys, dcN)`` with a column axis after the
        saved-point axis of ``dys`` and in front of ``dcN``. ``dys`` is a list: the
        observations whose kind in ``mo`` (`obs_kinds`) is not `OBS_ZERO`, as their kind
        stores them (`_obs_tangent`). Rotations' tangents are
        nine numbers here whatever ``mc`` says (`FRAME`): three numbers as small arrays
        of their own made the program about 1.8x slower on a CPU (more kernels).
        """
        mc = _dense_mask(mc)
        tobs = functools.partial(self._jac_tobs, mP, mc, mo)

        def observe(x):
            P, c, dP, dc = x
            cols = jax.vmap(lambda dP, dc: tobs((P, c, dP, dc)))
            return self.observe(P, c), cols(dP, dc)

        body = functools.partial(self._jac_body, mP, mc)
        x, (ys, dys) = self._save_loop(body, observe, (P, c0, dP, dc0))
        return ys, x[1], dys, x[3]

    def _jac_body(self, mP, mc, x):
        """One step of `jac_array`: ``(P, c, dP, dc)`` -> the same after the step."""
        P, c, dP, dc = x
        tstep = functools.partial(self._tstep, mP, mc)
        cols = jax.vmap(lambda dP, dc: tstep((P, c, dP, dc)), out_axes=(None, None, 0, 0))
        return cols(dP, dc)

    def jac_step(self, mP, mc, Pj, cj):
        """`_jac_body` as a step of a loop with parameters ``(P, dP)`` and carry
        ``(c, dc)`` (`_settle_jacobian_tangents`)."""
        (P, dP), (c, dc) = Pj, cj
        _, c1, _, dc1 = self._jac_body(mP, _dense_mask(mc), (P, c, dP, dc))
        return c1, dc1

    def jac_scalar(self, mP, mc, mo, P, c0, dP, dc0, cut=None, batched=None, one=None):
        """`jac_array` as a scalarized program: tangent components are ``(n,)`` arrays.

        The carry leaves flagged `FRAME` in ``mc`` carry their tangents as `Frame`
        ``xi`` (three numbers a rotation, `so3jax._frames`) inside; in and out they are
        dense, as `jac_array`'s.
        """
        while any(_frame_flags(mc)):
            try:
                return self._jac_scalar(mP, mc, mo, P, c0, dP, dc0, cut, batched, one)
            except FrameError as e:  # those leaves' tangents come out dense: nine numbers
                at = [i for i, m in enumerate(mc) if m]
                dense = {at[j] for j in e.indices}
                mc = tuple(True if i in dense else m for i, m in enumerate(mc))
        return self._jac_scalar(mP, mc, mo, P, c0, dP, dc0, cut, batched, one)

    def _jac_scalar(self, mP, mc, mo, P, c0, dP, dc0, cut, batched, one):
        fr = _frame_flags(mc)
        if any(fr):
            dc0 = _to_frames(_pick(mc, _floats(c0)), list(dc0), fr)
        col = jax.tree.map(lambda a: a[0], (dP, dc0))  # one column: the example
        ex = (P, c0) + col
        n_primal = len(sc.split((P, c0)))
        n_tangent = sum(math.prod(jnp.shape(a)) for a in jax.tree.leaves(col))
        n = jnp.shape(jax.tree.leaves((dP, dc0))[0])[0]
        # One column here: `_columns_outside` batches the tangents over the columns
        # around this program, and its cuts count that (`sc._eval_with_cuts`).
        columns = None
        if n == 1 and _TRACING[-1][0] >= COLUMN_CUTS_FROM:
            columns = [False] * n_primal + [True] * n_tangent
        body, _ = sc.flat_program(functools.partial(self._tstep, mP, mc), ex, cut, columns=columns)
        tobs, tobs_struct = sc.flat_program(
            functools.partial(self._jac_tobs, mP, mc, mo), ex, cut, columns=columns
        )
        obs, obs_struct = sc.flat_program(lambda x: self.observe(x[0], x[1]), ex, cut)
        flat0 = sc.split((P, c0)) + jax.vmap(sc.split)((dP, dc0))
        if n == 1:  # one column (`_columns_outside`): scalar tangent components
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
        flat, (ys, dys) = _hoisted(functools.partial(self._save_loop, vbody, observe), flat0)
        _, cN = sc.join(flat[:n_primal], jax.eval_shape(lambda: (P, c0)))
        if n == 1:
            flat = flat[:n_primal] + [x[None] for x in flat[n_primal:]]
        _, dcN = sc.join(flat[n_primal:], jax.eval_shape(lambda: col), (n,))
        if any(fr):
            dcN = _from_frames(_pick(mc, _floats(cN)), list(dcN), fr)
        ys = sc.join(ys, obs_struct, (self.n_save,))
        return ys, cN, sc.join(dys, tobs_struct, (self.n_save, n)), dcN

    # ---------------- adjoint (reverse mode) ----------------

    def _masked_step(self, P, c, j):
        """One step, or nothing past the end (the last segment is padded)."""
        c1 = self.step(P, c)
        return jax.tree.map(lambda a, b: jnp.where(j < self.n, a, b), c1, c)

    def _vjp_step(self, x):
        """Cotangents through step ``j`` and the observation after it, accumulated.

        ``x = (P, c_j, lam, acc, ct_obs, is_save, valid)``: ``lam`` is the
        cotangent of the state after step ``j`` (from later steps), ``ct_obs``
        the cotangent of the observation of that state (used where ``is_save``).
        Returns the cotangent of ``c_j`` and ``acc`` plus the parameters' share.
        """
        P, c, lam, acc, ct_o, is_save, valid = x

        def h(Pf, cf):
            Pp = _with_floats(P, Pf)
            c1 = self.step(Pp, _with_floats(c, cf))
            return _floats(c1), self.observe(Pp, c1)

        _, pull = jax.vjp(h, _floats(P), _floats(c))
        ct_o = jax.tree.map(lambda a: a * is_save.astype(a.dtype), ct_o)
        gP, gc = pull((lam, ct_o))
        lam = [jnp.where(valid, g, l) for g, l in zip(gc, lam, strict=True)]
        acc = [a + jnp.where(valid, g, jnp.zeros_like(g)) for a, g in zip(acc, gP, strict=True)]
        return lam, acc

    def _segment_cts(self, ct_obs, s):
        """Observation cotangents for the steps of segment ``s`` (zero off save points)."""
        j = s * self.K + jnp.arange(self.K)
        m = (j + 1) // self.save_every - 1
        is_save = ((j + 1) % self.save_every == 0) & (j < self.n)
        m = jnp.clip(m, 0, self.n_save - 1)
        return j, jax.tree.map(lambda a: a[m], ct_obs), is_save

    def adj_array(self, P, c0, ct_obs, ct_cN):
        K, S = self.K, self.S

        def advance(c, s):  # one segment, saving nothing
            def one(c, i):
                return self._masked_step(P, c, s * K + i), None

            return jax.lax.scan(one, c, jnp.arange(K))[0], c

        _, ckpts = jax.lax.scan(advance, c0, jnp.arange(S))

        def segment(carry, s_ck):
            lam, acc = carry
            s, ck = s_ck

            def one(c, i):
                return self._masked_step(P, c, s * K + i), c

            _, states = jax.lax.scan(one, ck, jnp.arange(K))
            j, cts, is_save = self._segment_cts(ct_obs, s)

            def back(carry, x):
                lam, acc = carry
                c, ct_o, sv, jj = x
                return self._vjp_step((P, c, lam, acc, ct_o, sv, jj < self.n)), None

            (lam, acc), _ = jax.lax.scan(back, (lam, acc), (states, cts, is_save, j), reverse=True)
            return (lam, acc), None

        acc0 = [jnp.zeros_like(p) for p in _floats(P)]
        (lam, acc), _ = jax.lax.scan(
            segment, (list(ct_cN), acc0), (jnp.arange(S), ckpts), reverse=True
        )
        return acc, lam

    def adj_scalar(self, P, c0, ct_obs, ct_cN, cut=None):
        K, S = self.K, self.S
        j0 = jnp.zeros((), jnp.int32)
        ex_step = (P, c0, j0)
        mstep, _ = sc.flat_program(lambda x: (x[0], self._masked_step(*x), x[2] + 1), ex_step, cut)
        nP = len(sc.split(P))
        nc = len(sc.split(c0))

        def advance_flat(fc, s, keep):
            """K masked steps from the flat state ``fc``; the states before each if ``keep``."""
            flat = sc.split(P) + fc + [jnp.asarray(s * K, jnp.int32)]

            def one(f, _):
                return mstep(f), (f[nP : nP + nc] if keep else None)

            f, ys = jax.lax.scan(one, flat, None, length=K)
            return f[nP : nP + nc], ys

        def ckpt(fc, s):
            return advance_flat(fc, s, False)[0], fc

        _, ck_flat = jax.lax.scan(ckpt, sc.split(c0), jnp.arange(S))

        lam0 = list(ct_cN)
        acc0 = [jnp.zeros_like(p) for p in _floats(P)]
        ct_o_ex = jax.tree.map(lambda a: a[0], ct_obs)
        ex_back = (P, c0, lam0, acc0, ct_o_ex, jnp.array(True), jnp.array(True))
        back_flat, _ = sc.flat_program(self._vjp_step, ex_back, cut)
        n_lam = len(sc.split(lam0))
        n_acc = len(sc.split(acc0))

        def segment(carry, s_ck):
            flam, facc = carry
            s, fck = s_ck
            _, states = advance_flat(list(fck), s, True)
            j, cts, is_save = self._segment_cts(ct_obs, s)

            def back(carry, x):
                flam, facc = carry
                fc, ct_o, sv, jj = x
                flat = sc.split(P) + list(fc) + flam + facc + sc.split(ct_o) + [sv, jj < self.n]
                out = back_flat(flat)
                return (out[:n_lam], out[n_lam : n_lam + n_acc]), None

            (flam, facc), _ = jax.lax.scan(
                back, (flam, facc), (states, cts, is_save, j), reverse=True
            )
            return (flam, facc), None

        (flam, facc), _ = jax.lax.scan(
            segment, (sc.split(lam0), sc.split(acc0)), (jnp.arange(S), ck_flat), reverse=True
        )
        lam = sc.join(flam, jax.eval_shape(lambda: lam0))
        acc = sc.join(facc, jax.eval_shape(lambda: acc0))
        return acc, lam


# --------------------------------------------------------------------------
# linear_call under vmap
# --------------------------------------------------------------------------


def _linear_call_batches() -> bool:
    """Whether so3jax's own batching ``linear_call`` primitive (`so3jax._linear_call`) is
    available; where it is not, the engine runs its reference programs and says so once."""
    if not _linear_call.AVAILABLE:  # pragma: no cover - a JAX release that moved the tables
        warnings.warn(
            "so3jax: this JAX release lacks the rule tables so3jax's linear_call primitive "
            "needs (jax.interpreters.ad / batching / mlir); derivatives run as JAX's "
            "autodiff of the array program (slower: the one-pass Jacobian and the discrete "
            "adjoint are off)",
            stacklevel=2,
        )
    return _linear_call.AVAILABLE


_HAVE_LINEAR_CALL_BATCHING = _linear_call_batches()


# --------------------------------------------------------------------------
# the entry point
# --------------------------------------------------------------------------


_PROGRAMS = ("auto", "array", "scalar", "autodiff", "adjoint")


def run(
    step: Callable,
    observe: Callable,
    params,
    carry0,
    n_steps: int,
    save_every: int = 1,
    *,
    checkpoint: int | None = None,
    program: str = "auto",
):
    """Step ``carry0`` ``n_steps`` times; observe every ``save_every``-th state.

    **Arguments:**

    - `step`: ``step(params, carry) -> carry``, one step (pure; a carry may
      hold integer leaves such as a step counter and a status code).
    - `observe`: ``observe(params, carry) -> pytree`` of float arrays.
    - `params`: a pytree of arrays the loop depends on; its float leaves (and
      those of ``carry0``) are what derivatives flow to.
    - `n_steps`, `save_every`: Python ints, ``n_steps % save_every == 0``.
    - `checkpoint`: steps per checkpointed segment of the adjoint (default
      about ``sqrt(n_steps)``; ``n_steps`` keeps every state).
    - `program`: ``"auto"`` (the engine decides, see the module docstring);
      ``"array"`` or ``"scalar"`` (one layout for the forward run whatever the
      batching, derivatives from JAX's ``jvp`` of the checkpointed array
      program: for benchmarks); ``"autodiff"`` (the checkpointed array
      program, differentiated and batched by JAX alone: the reference);
      ``"adjoint"`` (derivatives from the engine's tangent program and, in
      reverse mode, always its discrete adjoint; layouts per `BATCHED_LAYOUT`).

    **Returns:** ``(observations, final carry)``; every observation leaf has a
    leading axis of length ``n_steps // save_every`` (the states after steps
    ``save_every, 2 save_every, ...``).
    """
    if program not in _PROGRAMS:
        raise ValueError(f"program must be one of {_PROGRAMS}, got {program!r}")
    K = checkpoint_length(n_steps) if checkpoint is None else int(checkpoint)
    # Closed-over tracers (a reference that closes over a traced amplitude, say)
    # become explicit parameters, so derivatives and batching see them.
    step_c, step_consts = jax.closure_convert(step, params, carry0)
    obs_c, obs_consts = jax.closure_convert(observe, params, carry0)
    P = (params, step_consts, obs_consts)

    def step_p(P, c):
        return step_c(P[0], c, *P[1])

    def obs_p(P, c):
        return obs_c(P[0], c, *P[2])

    loop = _Loop(step_p, obs_p, n_steps, save_every, K)
    if program != "autodiff" and not _jax.supported():
        _jax.warn_reference_path()
        program = "autodiff"
    _plan.note("loop", n_steps=n_steps, save_every=save_every, program=program)
    if program == "autodiff":
        return loop.fwd_checkpointed(P, carry0)
    if program in ("auto", "adjoint") and _HAVE_LINEAR_CALL_BATCHING:
        return _adjoint_run(loop, P, carry0, reverse=program)
    if program == "array":  # batched by `_dual` too, so every output is (`_batched_with`)
        fwd = _dual(loop.fwd_array, loop.fwd_array, "array")
    elif program == "scalar":
        fwd = _dual(_scalar_or_array(loop), loop.fwd_scalar, "scalar")
    else:
        fwd = _dual(loop.fwd_array, loop.fwd_scalar, "run")

    # Derivatives: JAX's own jvp of the checkpointed array program (forward mode
    # as one fused scan; reverse mode by JAX's transpose, memory ~sqrt(n)).
    @jax.custom_jvp
    def f(P, c0):
        return fwd(P, c0)

    f.defjvp(functools.partial(_checkpointed_jvp, loop), symbolic_zeros=True)
    return f(P, carry0)


def _checkpointed_jvp(loop: _Loop, primals, tangents):
    """JAX's own ``jvp`` of the checkpointed array program, through the nonzero tangents.

    Only the inputs with nonzero tangents are differentiated: dense zero tangents
    for every other array would add a tangent term to each operation that touches
    them (35 % more time for DiffTune's jacfwd). Under ``grad`` JAX transposes it
    with symbolic zeros for the outputs a cost does not use, so their backward pass
    is pruned.
    """
    p_leaves, treedef = jax.tree.flatten(primals)
    t_leaves, nz = _tangent_leaves(tangents)
    n = sum(math.prod(jnp.shape(t)) for t, z in zip(t_leaves, nz, strict=True) if z)
    _plan.note(
        "derivative",
        strategy="checkpointed jvp",
        scalars=n,
        why=f"more than FORWARD_JACOBIAN_MAX = {FORWARD_JACOBIAN_MAX} scalars, or a "
        "program that asks for JAX's derivative",
    )
    t_leaves, nz = _settle_carry_tangents(loop.step, primals, p_leaves, t_leaves, nz)
    out, tan = _jvp_through(loop.fwd_checkpointed, treedef, p_leaves, t_leaves, nz)
    return _batched_with(out, primals), tan  # batched as the run's forward programs are


def _settle_carry_tangents(step, primals, p_leaves, t_leaves, nz) -> tuple[list, list]:
    """``(t_leaves, nz)`` with a zero tangent, not a symbolic one, for each initial carry
    leaf that a step gives a nonzero tangent (`_tangent_masks`), flagged nonzero.

    JAX's ``jvp`` of a ``scan`` finds which carry tangents are nonzero by
    differentiating the body until nothing changes, and under ``grad`` its partial
    evaluator finds the unknown carry the same way; in the checkpointed program the
    inner loop is differentiated again on every pass of the outer one. Starting those
    leaves with a zero tangent settles both in one pass. The zero is computed from an
    input tangent (`_zero_like_tangent`), so the partial evaluator sees it as unknown too.
    """
    P, c0 = primals
    n_P = len(jax.tree.leaves(P))
    floats = [_is_float(x) for x in p_leaves]
    nz_P, nz_c = _pick(floats[:n_P], nz[:n_P]), _pick(floats[n_P:], nz[n_P:])
    sources = [t for t, z, f in zip(t_leaves, nz, floats, strict=True) if z and f and t.size]
    if not sources or all(nz_c):
        return t_leaves, nz
    _, mc = _tangent_masks(step, P, c0, nz_P, nz_c)
    it = iter(mc)
    t_leaves, nz = list(t_leaves), list(nz)
    for i in range(n_P, len(p_leaves)):
        if floats[i] and next(it) and not nz[i]:
            t_leaves[i], nz[i] = _zero_like_tangent(p_leaves[i], sources[0]), True
    return t_leaves, nz


def _settle_jacobian_tangents(loop: _Loop, mP, mc, primals, p_leaves, t_leaves, nz):
    """`_settle_carry_tangents` for the Jacobian program (`_Loop.jac_array`), whose
    arguments ``(P, c0, dP, dc0)`` are a loop's parameters ``(P, dP)`` and its carry
    ``(c0, dc0)``: the carry tangents of second derivatives (`_dual_jvp`)."""
    sizes = [len(jax.tree.leaves(x)) for x in primals]
    a, b, c = np.cumsum(sizes)[:3].tolist()
    order = [*range(a), *range(b, c), *range(a, b), *range(c, len(p_leaves))]
    P, c0, dP, dc0 = primals
    t, z = _settle_carry_tangents(
        functools.partial(loop.jac_step, mP, mc),
        ((P, dP), (c0, dc0)),
        [p_leaves[i] for i in order],
        [t_leaves[i] for i in order],
        [nz[i] for i in order],
    )
    back = np.argsort(order).tolist()
    return [t[i] for i in back], [z[i] for i in back]


def _batched_with(out, inputs):
    """``out`` with a zero added to each numeric leaf, computed from every numeric leaf
    of ``inputs``: under ``vmap``, every output is batched wherever an input is.

    A ``custom_jvp`` function and its rule must agree on which outputs a batch
    batches: ``vmap`` of a jitted run batches the function alone (its jaxpr), and
    a later ``jvp`` of that batched program runs the rule in its place. The
    engine's forward programs batch every output (`_dual`'s ``custom_vmap``
    rule, ``program="array"`` included); JAX's ``jvp`` of the checkpointed array
    program batches only the outputs that depend on a batched input or tangent
    (the run's times, say, do not), so `_checkpointed_jvp` passes its outputs
    through here. Without it, ``jacfwd`` and ``grad`` of the mean of a ``vmap`` over
    the quadrotor's 12 gains raised "Cannot concatenate arrays with different
    numbers of dimensions". The zeros are ``where(False, ...)``
    (not ``0 * x``: an infinite input stays out of the values), which XLA folds.
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


_ADJOINT_FIRST_ORDER = (
    'program="adjoint" has first derivatives only; for second derivatives '
    '(jax.hessian, jvp or jacfwd of grad) use program="auto" (the default)'
)

#: Through at most this many differentiated scalars the run computes its Jacobian
#: with its value, in one pass (`_jacobian_jvp`), for forward and reverse mode alike.
FORWARD_JACOBIAN_MAX = 8

#: Whether the Jacobian programs carry attitude tangents as three numbers
#: (`so3jax._frames`); off: nine, from JAX's ``jvp`` (for benchmarks and tests).
FRAME_TANGENTS = os.environ.get("SO3JAX_FRAME_TANGENTS", "1") != "0"


def _adjoint_run(loop: _Loop, P, carry0, reverse: str = "adjoint"):
    """The run with the engine's own tangent program and a custom reverse mode.

    With ``reverse="auto"`` and at most `FORWARD_JACOBIAN_MAX` differentiated
    scalars, the derivative is the Jacobian of the run, computed with its value
    in one pass (`_Loop.jac_array` / `_Loop.jac_scalar`: the primal once, the
    ``n`` unit tangents batched over it); the tangent is then the Jacobian times
    the input tangent, which JAX transposes for reverse mode by itself. Through
    more scalars, JAX's own ``jvp`` of the checkpointed array program
    (`_checkpointed_jvp`), transposed by JAX in reverse mode. ``reverse="adjoint"``:
    the tangent program (`_Loop.tan_array` / `_Loop.tan_scalar`) and the discrete
    adjoint (`_Loop.adj_array` / `_Loop.adj_scalar`) whatever the number of inputs.
    """
    fwd = _dual(loop.fwd_array, loop.fwd_scalar, "run")
    adj = _dual(loop.adj_array, loop.adj_scalar, "adjoint")

    @jax.custom_jvp
    def f(P, c0):
        return fwd(P, c0)

    def f_jvp(primals, tangents):
        P, c0 = primals
        dP, dc0 = tangents
        tl = _floats_with_zeros((dP, dc0), (P, c0))
        nz = [not isinstance(t, SymbolicZero) for t in tl]
        lin = [t for t, z in zip(tl, nz, strict=True) if z]
        pf, cf = _floats(P), _floats(c0)
        if not lin:
            out = fwd(P, c0)
            dys = jax.tree.map(jnp.zeros_like, out[0])
            return out, (dys, _tangent_tree(out[1], [jnp.zeros_like(x) for x in _floats(out[1])]))
        n_lin = sum(math.prod(jnp.shape(x)) for x in lin)
        if reverse == "auto" and n_lin > FORWARD_JACOBIAN_MAX:
            return _checkpointed_jvp(loop, primals, tangents)
        if reverse == "auto":
            _plan.note(
                "derivative",
                strategy="one-pass Jacobian",
                scalars=n_lin,
                why=f"at most FORWARD_JACOBIAN_MAX = {FORWARD_JACOBIAN_MAX} scalars",
            )
            mP, mc, elements = _tangent_masks(
                loop.step, P, c0, nz[: len(pf)], nz[len(pf) :], elements=True
            )
            return _jacobian_jvp(loop, P, c0, nz, lin, mP, mc, elements)
        mP, mc = _tangent_masks(loop.step, P, c0, nz[: len(pf)], nz[len(pf) :])
        _plan.note(
            "derivative", strategy="discrete adjoint", scalars=n_lin, why='program="adjoint"'
        )
        out = fwd(P, c0)
        tan = _dual(
            functools.partial(loop.tan_array, mP, mc),
            functools.partial(loop.tan_scalar, mP, mc),
            "tangent",
        )

        def tangent(res, lin):
            P, c0 = res
            dys, dcN = tan(P, c0, *_masked_tangents(nz, lin, mP, mc, pf, cf))
            return dys, _fill(mc, dcN, [jnp.zeros_like(x) for x in _floats(out[1])])

        def transpose(res, cts):
            P, c0 = res
            ct_ys, ct_cN = cts
            gP, gc = adj(P, c0, ct_ys, ct_cN)
            return [g for g, z in zip(list(gP) + list(gc), nz, strict=True) if z]

        dys, dcNf = linear_call(
            tangent, transpose, first_order_only(_ADJOINT_FIRST_ORDER, (P, c0)), lin
        )
        return out, (dys, _tangent_tree(out[1], dcNf))

    f.defjvp(f_jvp, symbolic_zeros=True)
    return f(P, carry0)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def first_order_only(why: str, res):
    """``res`` (residuals of a ``linear_call``) unchanged; ``NotImplementedError(why)``
    if they are differentiated, as in a second derivative: ``linear_call`` cannot
    differentiate its residuals, and failed with a bare ``AssertionError``."""
    return res


@first_order_only.defjvp
def _first_order_only_jvp(why, primals, tangents):
    raise NotImplementedError(why)


def _jacobian_jvp(loop: _Loop, P, c0, nz: list, lin: list, mP: tuple, mc: tuple, elements: list):
    """The run's value and tangent from its Jacobian, computed in one pass.

    ``lin`` (the nonzero input tangents, ``n`` scalars in all) is flattened into
    a coefficient vector; the Jacobian program runs the unit tangents as ``n``
    columns over one primal (no residuals, nothing recomputed), and the tangent
    is each column scaled by its coefficient. Under ``jacfwd`` the columns are
    computed once for every basis vector; under ``grad`` JAX transposes the
    contraction. The same program runs scalarized under ``vmap`` of 16 runs or
    more (`BATCHED_LAYOUT`).

    ``elements`` (`_tangent_masks`) and the frame rules decide, per observation, what
    the loop saves (`_Loop.obs_kinds`): nothing where the tangent is zero (the
    reference attitude of a gain's derivative), three numbers a column for a rotation.
    A seed trajectory's columns take 15 numbers a point instead of 25.
    """
    pf, cf = _floats(P), _floats(c0)
    cols = _unit_columns(lin)
    n = len(cols[0])
    mc = _with_frames(mc, c0, nz[len(pf) :])
    mo = loop.obs_kinds(mP, mc, P, c0, elements)
    dP, dc = _masked_tangents(nz, cols, mP, mc, pf, cf, (n,))
    jac = _dual(
        functools.partial(loop.jac_array, mP, mc, mo),
        functools.partial(loop.jac_scalar, mP, mc, mo),
        "jacobian",
        settle=functools.partial(_settle_jacobian_tangents, loop, mP, mc),
    )
    ys, cN, Jys, JcN = jac(P, c0, dP, dc)
    coef = jnp.concatenate([jnp.ravel(x) for x in lin])

    # Observations without a tangent get zeros here (the loop neither computes nor saves
    # them); frames become dense here, where their three numbers are contracted first.
    J_it = iter(Jys)
    dys = []
    for y, kind in zip(jax.tree.leaves(ys), mo, strict=True):
        if kind == OBS_ZERO:  # symbolic: no zeros are made, batched or masked downstream
            dys.append(SymbolicZero(jax.typeof(y).to_tangent_aval()))
            continue
        J = next(J_it)
        d = jnp.tensordot(coef.astype(J.dtype), J, axes=([0], [1]))
        dys.append(d if kind == OBS_DENSE else _frame_dense(y, d, kind == OBS_LEFT))
    dys = jax.tree.unflatten(jax.tree.structure(ys), dys)
    dcN = [jnp.tensordot(coef.astype(J.dtype), J, axes=1) for J in JcN]
    dcNf = _fill(mc, dcN, [jnp.zeros_like(x) for x in _floats(cN)])
    return (ys, cN), (dys, _tangent_tree(cN, dcNf))


def _frame_dense(R, xi, left: bool):
    """``R hat(xi)`` (``left``: ``hat(xi) R``) for ``xi`` of shape ``R.shape[:-1]``, written
    with splits and concatenations only, so that JAX's transpose (``grad`` of a cost on the
    saved rotations) is elementwise too.

    `so3jax._frames.dense` broadcasts ``xi`` over ``R``'s rows and slices both; JAX
    transposes the broadcast into a sum over an axis of three (which XLA's CPU compiler
    hands to a library reduction) and each slice into a pad. Here ``xi`` is concatenated
    three times (transposed: three slices added) and components are split (transposed:
    concatenated).
    """
    if left:  # hat(xi) R = -(R^T hat(xi))^T
        return -jnp.swapaxes(_frame_dense(jnp.swapaxes(R, -1, -2), xi, False), -1, -2)
    X = jnp.concatenate([xi[..., None, :].astype(R.dtype)] * 3, axis=-2)
    r0, r1, r2 = jnp.split(R, 3, axis=-1)
    x0, x1, x2 = jnp.split(X, 3, axis=-1)  # rows of R hat(xi) are r_i x xi
    return jnp.concatenate([r1 * x2 - r2 * x1, r2 * x0 - r0 * x2, r0 * x1 - r1 * x0], axis=-1)


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


def _scalar_or_array(loop: _Loop) -> Callable:
    """The scalarized forward program, or the array one (with a warning) if it cannot be."""

    def fwd(P, c0):
        try:
            return loop.fwd_scalar(P, c0)
        except sc.ScalarizeError as e:
            warnings.warn(f"{e}; running the array program instead", stacklevel=4)
            return loop.fwd_array(P, c0)

    return fwd


def _floats_with_zeros(tangents, primals) -> list:
    """Tangents of the float leaves of ``primals`` (symbolic zeros kept)."""
    t_leaves = jax.tree.leaves(tangents, is_leaf=lambda x: isinstance(x, SymbolicZero))
    p_leaves = jax.tree.leaves(primals)
    return [t for t, p in zip(t_leaves, p_leaves, strict=True) if _is_float(p)]
