"""Derivative strategies: how a run's derivative is computed, as objects.

A run (`so3jax._engine.run`) is one ``jax.custom_jvp`` whose rule asks `choose` for a
`Strategy`. The three agree to round-off (docs/engine.md, "Derivatives"):

- `Autodiff`: JAX's ``jvp`` of the checkpointed array program
  (`so3jax._engine.loop.Loop.fwd_checkpointed`); the reference.
- `OnePassJacobian`: through at most ``forward_jacobian_max`` scalars, the value and its
  Jacobian in one pass; nothing stored per step.
- `CheckpointedAdjoint`: through more (any number with ``program="adjoint"``),
  `Autodiff`'s ``jvp`` forward and the engine's discrete adjoint in reverse mode.

`Flagged`, `ForwardColumns` and `CustomTranspose` serve programs outside the fixed-step
engine (`so3jax.simulate` with tolerances, a ``while_loop``).

References: A. Griewank, A. Walther, *Evaluating Derivatives*, SIAM 2008 (vector
forward mode and discrete adjoints, ch. 3; checkpointing, ch. 12).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from .._so3 import _FULL
from . import plan as _plan
from .layout import _dual
from .linear_call import linear_call
from .masks import _tangent_masks
from .passes import scalarized, settle
from .passes.frames import OBS_DENSE, OBS_LEFT, OBS_NAMES, OBS_ZERO, _frame_dense, _with_frames
from .policy import current
from .programs import Programs
from .tangents import (
    _float_tangent,
    _jvp_through,
    _linear_tangent,
    _with_float0,
    first_order_only,
    forward_differentiated,
)
from .trees import (
    _batched_with,
    _fill,
    _floats,
    _floats_with_zeros,
    _is_float,
    _masked_tangents,
    _pick,
    _tangent_leaves,
    _tangent_tree,
    _unit_columns,
)

__all__ = [
    "Strategy",
    "Autodiff",
    "OnePassJacobian",
    "CheckpointedAdjoint",
    "choose",
    "differentiated",
    "Flagged",
    "ForwardColumns",
    "CustomTranspose",
    "tangent_tree",
    "float_leaves",
    "jvp_through",
]


class Strategy:
    """How a run's derivative is computed.

    `jvp` is a ``custom_jvp`` rule (``symbolic_zeros=True``) given the loop, the forward
    program ``fwd(P, c0) -> (observations, final carry)``, the primals and tangents."""

    name: str = ""

    def jvp(self, loop: Programs, fwd: Callable, primals, tangents):
        raise NotImplementedError

    def _settled(self, loop: Programs, primals, tangents):
        """``(leaves, treedef, t_leaves, nz, real)`` of the rule's inputs, noted in the plan:
        ``real`` flags the nonzero tangents, ``nz`` those and the carry tangents the
        ``"settle"`` pass starts with zeros (`settle.carry_tangents`)."""
        p_leaves, treedef = jax.tree.flatten(primals)
        t_leaves, real = _tangent_leaves(tangents)
        n = _size(_pick(real, t_leaves))
        _plan.note("derivative", strategy=self.name, scalars=n, why=self.why)
        t_leaves, nz = settle.carry_tangents(
            loop.step, primals, p_leaves, t_leaves, real, loop.jaxprs
        )
        return p_leaves, treedef, t_leaves, nz, real


@dataclasses.dataclass(frozen=True)
class Autodiff(Strategy):
    """JAX's own ``jvp`` of the checkpointed array program, through the nonzero tangents.
    ``why``: the reason `so3jax.explain` shows."""

    why: str = "JAX's derivative of the reference program"
    name = "checkpointed jvp"

    def jvp(self, loop, fwd, primals, tangents):
        p_leaves, treedef, t_leaves, nz, _ = self._settled(loop, primals, tangents)
        out, tan = _jvp_through(loop.fwd_checkpointed, treedef, p_leaves, t_leaves, nz)
        return _batched_with(out, primals), tan  # batched as the run's forward programs are


@dataclasses.dataclass(frozen=True)
class OnePassJacobian(Strategy):
    """The run's value and its Jacobian in one pass (`_jacobian_jvp`); through at most the
    policy's ``forward_jacobian_max`` differentiated scalars."""

    name = "one-pass Jacobian"

    def jvp(self, loop, fwd, primals, tangents):
        P, c0 = primals
        nz, lin = _nonzero(primals, tangents)
        n_pf = len(_floats(P))
        mP, mc, elements = _tangent_masks(
            loop.step, P, c0, nz[:n_pf], nz[n_pf:], elements=True, cache=loop.jaxprs
        )
        _plan.note(
            "derivative",
            strategy=self.name,
            scalars=_size(lin),
            carried=tuple(mc),
            why=f"at most forward_jacobian_max = {current().forward_jacobian_max} scalars",
        )
        return _jacobian_jvp(loop, P, c0, nz, lin, mP, mc, elements)


@dataclasses.dataclass(frozen=True)
class CheckpointedAdjoint(Strategy):
    """Through more than ``forward_jacobian_max`` scalars (any number with
    ``program="adjoint"``): JAX's ``jvp`` of the checkpointed array program in forward mode
    and for second derivatives, the discrete adjoint in reverse mode.

    A ``linear_call`` (`_linear_tangent`) transposed by `_adjoint_transpose` over what
    `_adjoint_forward` saves. ``why``: the reason `so3jax.explain` shows.
    """

    why: str = "more than forward_jacobian_max scalars"
    name = "checkpointed jvp, discrete adjoint"

    def jvp(self, loop, fwd, primals, tangents):
        p_leaves, treedef, t_leaves, nz, real = self._settled(loop, primals, tangents)
        P, c0 = primals
        floats = [_is_float(x) for x in p_leaves]
        nz = [z and f for z, f in zip(nz, floats, strict=True)]
        n_P = len(jax.tree.leaves(P))
        nz_P, nz_c = _pick(floats[:n_P], nz[:n_P]), _pick(floats[n_P:], nz[n_P:])
        mP, mc = _tangent_masks(loop.step, P, c0, nz_P, nz_c, cache=loop.jaxprs)
        out, saved, layout = _adjoint_forward(loop, fwd, mP, mc, P, c0)
        out_nz = [_is_float(o) for o in jax.tree.leaves(out)]
        n_ys = len(jax.tree.leaves(out[0]))
        avals = jax.eval_shape(lambda: out)

        def adjoint(res, cts):  # cts: the float outputs' cotangents, None for symbolic zeros
            P, c0 = jax.tree.unflatten(treedef, res[1])
            gP, gc = _adjoint_transpose(
                loop, mP, mc, layout, P, c0, avals, cts[:n_ys], cts[n_ys:], res[2]
            )
            return _pick(nz, _fill(floats, gP + gc, [None] * len(floats)))

        # Forward mode: JAX's jvp of the checkpointed program (docs/engine.md).
        plain = _float_tangent(loop.fwd_checkpointed, treedef, nz, out_nz)
        xs, ts = _pick(nz, p_leaves), _pick(nz, t_leaves)
        tan = _linear_tangent(
            plain,
            plain,
            xs,
            p_leaves,
            ts,
            _pick(nz, real),
            adjoint=adjoint,
            extra=saved,
            out_shapes=_pick(out_nz, jax.tree.leaves(out)),  # (their shapes alone)
        )
        return out, _with_float0(out, out_nz, tan)


def _adjoint_forward(loop: Programs, fwd: Callable, mP, mc, P, c0):
    """``(out, saved, layout)``: the run's value and what its discrete adjoint reads.

    Every step's residuals (`Programs.fwd_residuals`, ``layout`` their packing) within
    the policy's ``adjoint_residual_bytes`` per run; else the segments' starting carries
    (`Programs.fwd_segments`, ``layout`` ``None``; nothing for one segment)."""
    steps, budget = loop.n, current().adjoint_residual_bytes
    if budget > 0:  # the residuals' size is known once they are traced
        layout: list = []
        run = functools.partial(loop.fwd_residuals, mP, mc, layout)
        with _plan.deferred() as pending:  # dropped if the residuals are too large
            out, saved = _dual(run, run, "adjoint")(P, c0)
        per_step = sum(math.prod(a.shape[2:]) * a.dtype.itemsize for a in saved[0])
        if per_step * steps <= budget:
            _plan.extend(pending)
            _plan.note("adjoint", saved="residuals", bytes_per_step=per_step, steps=steps)
            return out, saved, layout
    if loop.segments > 1:  # the run and the adjoint's checkpoints in one pass (array layout)
        out, ck = _dual(loop.fwd_segments, loop.fwd_segments, "adjoint")(P, c0)
    else:
        out, ck = fwd(P, c0), None
    K = loop.blocks_per_segment * loop.save_every
    _plan.note("adjoint", saved="checkpoints", segments=loop.segments, steps_per_segment=K)
    return out, ck, None


def _adjoint_transpose(loop: Programs, mP, mc, layout, P, c0, avals, ct_ys, ct_cN, saved):
    """``(gP, gc)``: the discrete adjoint at ``ct_ys`` (per observation leaf) and ``ct_cN``
    (per float leaf of the final carry); ``None`` is a symbolic zero, left out of the
    backward pass. ``avals``: the shapes of ``(ys, cN)``; ``saved``, ``layout``: from
    `_adjoint_forward`."""
    keep = tuple(c is not None for c in ct_ys)
    kept = [c for c in ct_ys if c is not None]
    ct_cN = [
        jnp.zeros(a.shape, a.dtype) if c is None else c
        for c, a in zip(ct_cN, _floats(avals[1]), strict=True)
    ]
    # Array layout only (docs/engine.md, "The discrete adjoint and the reference programs").
    if layout is not None:
        adj = functools.partial(loop.adj_residuals, mP, mc, keep, layout)
        gP, gc = _dual(adj, adj, "adjoint")(P, saved, kept, ct_cN)
    else:
        adj = functools.partial(loop.adj_segments, mP, mc, keep)
        gP, gc = _dual(adj, adj, "adjoint")(P, c0, kept, ct_cN, saved)
    return list(gP), list(gc)


def _nonzero(primals, tangents) -> tuple[list, list]:
    """Per float leaf of ``primals``, whether its tangent is nonzero; the nonzero ones."""
    tl = _floats_with_zeros(tangents, primals)
    nz = [not isinstance(t, SymbolicZero) for t in tl]
    return nz, [t for t, z in zip(tl, nz, strict=True) if z]


def _size(xs) -> int:
    return sum(math.prod(jnp.shape(x)) for x in xs)


def choose(program: str, n_scalars: int) -> Strategy:
    """The strategy for a run of ``program`` differentiated through ``n_scalars`` scalars.

    ``"auto"``: `OnePassJacobian` through at most ``forward_jacobian_max`` scalars, else
    `CheckpointedAdjoint`; ``"adjoint"``: `CheckpointedAdjoint`; any other program:
    `Autodiff` (`so3jax._engine.run` takes every program there on a JAX release outside
    `so3jax._engine._jax.supported`).
    """
    if program not in ("auto", "adjoint"):
        return Autodiff(why="a program that asks for JAX's derivative")
    if program == "adjoint":
        return CheckpointedAdjoint(why='program="adjoint"')
    limit = current().forward_jacobian_max
    if n_scalars <= limit:
        return OnePassJacobian()
    return CheckpointedAdjoint(why=f"more than forward_jacobian_max = {limit} scalars")


def differentiated(loop: Programs, fwd: Callable, program: str) -> Callable:
    """``fwd`` (a run's forward program, ``(P, c0) -> (observations, final carry)``) with
    the derivative `choose` picks for ``program``, decided per call from the tangents."""

    @jax.custom_jvp
    def f(P, c0):
        return fwd(P, c0)

    def f_jvp(primals, tangents):
        nz, lin = _nonzero(primals, tangents)
        if not lin and program in ("auto", "adjoint"):
            out = fwd(*primals)
            dys = jax.tree.map(jnp.zeros_like, out[0])
            return out, (dys, _tangent_tree(out[1], [jnp.zeros_like(x) for x in _floats(out[1])]))
        return choose(program, _size(lin)).jvp(loop, fwd, primals, tangents)

    f.defjvp(f_jvp, symbolic_zeros=True)
    return f


def _jacobian_jvp(loop: Programs, P, c0, nz: list, lin: list, mP: tuple, mc: tuple, elements: list):
    """The run's value and tangent from its Jacobian, computed in one pass.

    The unit tangents of ``lin`` (the nonzero input tangents) run as columns over one
    primal, then are contracted with ``lin``. `Programs.obs_kinds` picks what each
    observation saves: nothing for a zero tangent, three numbers a column for a rotation.
    """
    pf, cf = _floats(P), _floats(c0)
    cols = _unit_columns(lin)
    n = len(cols[0])
    mc = _with_frames(mc, c0, nz[len(pf) :])
    mo = loop.obs_kinds(mP, mc, P, c0, elements)
    _plan.note("observations", saved=tuple(OBS_NAMES[k] for k in mo))
    dP, dc = _masked_tangents(nz, cols, mP, mc, pf, cf, (n,))
    jac = _dual(
        functools.partial(loop.jac_array, mP, mc, mo),
        functools.partial(scalarized.jacobian, loop, mP, mc, mo),
        "jacobian",
        settle=functools.partial(settle.jacobian_tangents, loop, mP, mc),
    )
    ys, cN, Jys, JcN = jac(P, c0, dP, dc)
    coef = jnp.concatenate([jnp.ravel(x) for x in lin])

    # Observations without a tangent become symbolic zeros; frames become dense here.
    J_it = iter(Jys)
    dys = []
    for y, kind in zip(jax.tree.leaves(ys), mo, strict=True):
        if kind == OBS_ZERO:
            dys.append(SymbolicZero(jax.typeof(y).to_tangent_aval()))
            continue
        J = next(J_it)
        d = jnp.tensordot(coef.astype(J.dtype), J, axes=([0], [1]), precision=_FULL)
        dys.append(d if kind == OBS_DENSE else _frame_dense(y, d, kind == OBS_LEFT))
    dys = jax.tree.unflatten(jax.tree.structure(ys), dys)
    dcN = [jnp.tensordot(coef.astype(J.dtype), J, axes=1, precision=_FULL) for J in JcN]
    dcNf = _fill(mc, dcN, [jnp.zeros_like(x) for x in _floats(cN)])
    return (ys, cN), (dys, _tangent_tree(cN, dcNf))


# -- the same pieces for programs outside the fixed-step engine --


@dataclasses.dataclass(frozen=True)
class Flagged:
    """A ``custom_jvp`` rule's inputs (``symbolic_zeros=True``) split into the leaves it
    differentiates (float leaves with a nonzero tangent: `xs`, tangents `ts`) and the rest.
    """

    leaves: list
    treedef: object
    nz: list
    t_leaves: list

    @classmethod
    def of(cls, primals, tangents) -> Flagged:
        leaves, treedef = jax.tree.flatten(primals)
        t_leaves, nonzero = _tangent_leaves(tangents)
        nz = [z and _is_float(x) for x, z in zip(leaves, nonzero, strict=True)]
        return cls(leaves, treedef, nz, t_leaves)

    @property
    def xs(self) -> list:
        return _pick(self.nz, self.leaves)

    @property
    def ts(self) -> list:
        return _pick(self.nz, self.t_leaves)

    @property
    def n(self) -> int:
        """The number of differentiated scalars."""
        return _size(self.xs)

    def pick(self, leaves: list) -> list:
        """The differentiated entries of ``leaves`` (every input's leaves, in order)."""
        return _pick(self.nz, leaves)

    def at(self, xs, others: list | None = None):
        """The inputs with the differentiated leaves ``xs``, the rest ``others`` (or primals)."""
        base = self.leaves if others is None else others
        return jax.tree.unflatten(self.treedef, _fill(self.nz, list(xs), base))


def jvp_through(fn: Callable, flagged: Flagged):
    """JAX's ``jvp`` of ``fn(*inputs)`` through ``flagged``'s differentiated leaves alone."""
    return _jvp_through(fn, flagged.treedef, flagged.leaves, flagged.t_leaves, flagged.nz)


def float_leaves(tree) -> list:
    """The float leaves of ``tree``, in order: what derivatives flow through."""
    return _floats(tree)


def tangent_tree(out, float_tangents):
    """A tangent pytree for ``out``: ``float_tangents`` for its float leaves (in order),
    ``float0`` zeros for integer and boolean ones."""
    return _tangent_tree(out, float_tangents)


@dataclasses.dataclass(frozen=True)
class ForwardColumns:
    """The one-pass Jacobian of a program JAX differentiates in forward mode.

    `jvp`: ``fn(xs, others)`` and its Jacobian times the tangents, the unit tangents of
    ``xs`` batched over one primal; reverse mode by columns (`forward_differentiated`).
    """

    def jvp(self, fn: Callable, flagged: Flagged):
        xs = flagged.xs

        def jacobian(xs, others):
            def g(*x):
                out = fn(x, others)
                return _floats(out), out

            def column(*ts):
                return jax.jvp(g, tuple(xs), ts, has_aux=True)[1:]

            dout, out = jax.vmap(column, out_axes=(0, None))(*_unit_columns(xs))
            return out, dout

        others = _fill(flagged.nz, [jnp.zeros_like(x) for x in xs], flagged.leaves)
        out, J = forward_differentiated(jacobian)(list(xs), others)
        coef = jnp.concatenate([jnp.ravel(t) for t in flagged.ts])
        dout = [jnp.tensordot(coef.astype(Jk.dtype), Jk, axes=1, precision=_FULL) for Jk in J]
        return out, _tangent_tree(out, dout)


@dataclasses.dataclass(frozen=True)
class CustomTranspose:
    """A tangent program with a transpose of one's own: ``tangent(res, ts)`` (linear in
    ``ts``) and ``transpose(res, cts)``, where ``res`` are every input's leaves.

    Neither may close over the rule's trace. A second derivative raises
    ``NotImplementedError(why)``."""

    why: str

    def jvp(self, out, tangent: Callable, transpose: Callable, flagged: Flagged):
        res = first_order_only(self.why, list(flagged.leaves))
        dout = linear_call(tangent, transpose, res, flagged.ts)
        return out, _tangent_tree(out, dout)
