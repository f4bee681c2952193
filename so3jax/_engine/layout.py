"""Layouts: the array program for one run, the scalarized one for a large batch.

`_dual(array_fn, scalar_fn, what)` switches between them: unbatched it runs ``array_fn``
(traced once, `_Traced`); under ``vmap`` its ``custom_vmap`` rule runs ``scalar_fn`` (the
``"scalarize"`` pass) from the policy's threshold for ``what`` on, in tiles (``"tiles"``)
where the policy says, and the vmapped array program below it. Its derivative (`_dual_jvp`)
differentiates the program the call runs. With the passes off, a batch is JAX's ``vmap`` of
the array program (docs/engine.md, "Two layouts of one program").
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap
from jax.extend import core as jex_core

from . import plan as _plan
from .passes import scalarize as sc, scalarized, settle as settle_pass
from .passes.cuts import cut_index
from .passes.hoist import _hoisted, _tracing
from .passes.tiles import _in_tiles, batch_tiles
from .policy import batched_layout
from .tangents import (
    _array_jvp,
    _float_tangent,
    _linear_tangent,
    _with_float0,
)
from .trees import (
    _batch_by,
    _batched_with,
    _front,
    _is_float,
    _pick,
    _tangent_leaves,
)


def _dual(
    array_fn: Callable, scalar_fn: Callable, what: str, settle=None, columns=None
) -> Callable:
    """``array_fn`` when unbatched; ``vmap`` of ``scalar_fn`` when batched.

    ``settle``: how `_dual_jvp` starts the carry tangents of the programs' loops (``None``:
    as JAX finds them). ``columns``: for the ``jvp`` of a Jacobian program, where its columns
    are (`scalarized.columns_outside`). Where ``scalar_fn`` raises `ScalarizeError` at trace
    time, a batch silently vmaps ``array_fn`` (the plan notes why).

    ``array_fn`` is traced once per call: the ``custom_vmap`` and its rule run one jaxpr
    (`_Traced`; tests/test_engine.py::test_batched_programs_are_traced_once). The call is a
    ``custom_jvp`` (`_dual_jvp`) so that second derivatives differentiate it and ``grad``
    binds it whole (docs/engine.md, "Second derivatives", "One custom JVP per run";
    tests/test_engine.py::test_second_derivatives_equal_autodiff).
    """

    array_fn = _plan.traced(array_fn, what)

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
                _plan.extend(traced.pending)
                _plan.note("layout", program=what, runs=1, layout="array")
            return out

    rule = functools.partial(_dual_jvp, array_fn, scalar_fn, what, settle)
    call.defjvp(rule, symbolic_zeros=True)
    return call


def _dual_jvp(array_fn: Callable, scalar_fn: Callable, what: str, settle, primals, tangents):
    """`_dual`'s derivative: second derivatives of a run differentiate its rule's programs.

    For ``"run"`` and ``"jacobian"``: the value is a `_dual` of the same programs and the
    tangent a ``linear_call`` (`_linear_tangent`) of the ``jvp`` of the program `_dual` would
    run, itself a `_dual` (``"jvp"``), so a batch's second derivatives run the batch's program.
    Other programs, and the ``"jvp"`` ones (third derivatives): JAX's ``jvp`` of the array
    program (`_array_jvp`). The ``linear_call``'s batching rule leaves a call with nothing
    batched unbatched (docs/engine.md, "so3jax's own linear_call").

    ``settle(primals, leaves, t_leaves, nz) -> (t_leaves, nz)`` starts the loops' carry
    tangents that a step makes nonzero with zeros (for the Jacobian program, the
    ``"settle"`` pass's `jacobian_tangents`), so JAX differentiates each loop body once.
    """
    _plan.note("derivative", strategy="second derivative", program=what)
    if what not in ("run", "jacobian"):
        return _array_jvp(array_fn, primals, tangents)
    leaves, treedef = jax.tree.flatten(primals)
    t_leaves, real = _tangent_leaves(tangents)
    t_leaves, nz = (t_leaves, real) if settle is None else settle(primals, leaves, t_leaves, real)

    out = _front(_batched_with(_dual(array_fn, scalar_fn, what, settle)(*primals), primals))
    # integer outputs (a run's status): float0 tangents, outside the linear_call
    out_nz = [_is_float(o) for o in jax.tree.leaves(out)]
    plain = _float_tangent(array_fn, treedef, nz, out_nz)
    columns = None
    if what == "jacobian":  # its columns outside the runs in the jvp program too
        in_cols, out_cols = scalarized.jacobian_columns(primals, jax.tree.structure(out))
        # the jvp program takes (xs, ts, others): differentiated leaves, tangents, all leaves
        xs_cols = _pick(nz, in_cols)
        columns = (xs_cols + xs_cols + in_cols, _pick(out_nz, out_cols))
    fast = _dual(plain, _float_tangent(scalar_fn, treedef, nz, out_nz), "jvp", columns=columns)
    xs, ts = _pick(nz, leaves), _pick(nz, t_leaves)
    # the tangents settle added are zeros, not real ones (`_linear_tangent`'s transpose)
    tan = _linear_tangent(plain, fast, xs, leaves, ts, _pick(nz, real))
    return out, _with_float0(out, out_nz, tan)


class _Traced:
    """A traced array program: called as it was traced, or batched with its loops settled.

    Under ``vmap`` with the ``"settle"`` pass, each loop's carry components that its body
    would batch are batched before it (`settle.batched_carries`), so JAX batches each body
    once; what never depends on the batch stays unbatched (docs/engine.md, "Loops that start
    settled"; tests/test_engine.py::test_batched_array_loops_start_settled).
    """

    def __init__(self, closed, out_tree):
        self.closed, self.out_tree = closed, out_tree
        self.pending = None

    def __call__(self, *args):
        # deferred: `_dual` keeps these decisions only if no batch rule replaces the call
        with _plan.deferred() as self.pending:
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
                body, batch = e.params["jaxpr"].jaxpr, lambda x: _batch_by(x, one)
                ins, bs = settle_pass.batched_carries(body, split, ins, bs, batch)
            params = e.primitive.get_bind_params(e.params)
            with e.ctx.manager:
                if e.primitive.name == "scan":
                    counts = sc.scan_split(e)  # (the parameters' names move between JAX releases)
                    xs_from = None if counts is None else sum(counts)
                    loop = functools.partial(e.primitive.bind, **params)
                    outs = _hoisted(loop, *ins, xs_from=xs_from)
                else:
                    outs = e.primitive.bind(*ins, **params)
            outs = outs if e.primitive.multiple_results else [outs]
            env.update(zip(e.outvars, outs, strict=True))
            batched.update(zip(e.outvars, sc.eqn_batched(e, bs), strict=True))
        return jax.tree.unflatten(self.out_tree, [read(v) for v in jaxpr.outvars])


def _dual_of(array_fn: "_Traced", scalar_fn: Callable, what: str, columns=None) -> Callable:
    fn = custom_vmap(array_fn)

    @fn.def_vmap
    def _rule(axis_size, in_batched, *args):
        columns, observed = 0, 1
        if what == "jacobian":
            columns = scalarized.column_count(args, in_batched, array_fn.out_tree)
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
        def array(why):
            _plan.note("layout", program=what, runs=axis_size, layout="array", why=why)
            return array_fn.vmap(axis_size, in_batched, args)

        axes = tuple(jax.tree.map(lambda b: 0 if b else None, ib) for ib in in_batched)
        scalar_from, cut_from = batched_layout(what)
        if scalar_from is None or axis_size < scalar_from:
            out = array(f"fewer runs than the scalarized layout's threshold {scalar_from}")
            return out, jax.tree.map(lambda _: True, out)
        try:
            cuts = cut_from is not None and axis_size >= cut_from
            index = cut_index(args) if cuts else None

            def runs(*args):
                if index is not None:
                    # the loops settle their carry's batching up front (`sc.settle_batched`)
                    def cut(one, *a):
                        return scalar_fn(*a, cut=index, batched=in_batched, one=one)

                    one = jnp.zeros((axis_size,), jnp.int32)
                    return jax.vmap(cut, in_axes=(0, *axes))(one, *args)
                return jax.vmap(functools.partial(scalar_fn, cut=index), in_axes=axes)(*args)

            cols = columns
            if what == "jacobian":
                cols = scalarized.jacobian_columns(args, array_fn.out_tree)
            if cols is not None:
                out = scalarized.columns_outside(runs, args, in_batched, *cols)
            else:
                out = runs(*args)
            _plan.note("layout", program=what, runs=axis_size, layout="scalarized", cuts=cuts)
        except sc.ScalarizeError as e:
            out = array(f"the step cannot be scalarized: {e}")
        return out, jax.tree.map(lambda _: True, out)

    return fn
