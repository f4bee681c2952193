"""Layouts: the array program for one run, the scalarized one for a large batch.

`_dual(array_fn, scalar_fn, what)` is the engine's switch between layouts: called
unbatched it runs ``array_fn`` (traced once, `_Traced`); under ``vmap`` its
``custom_vmap`` rule runs ``scalar_fn`` (the ``"scalarize"`` pass) from the policy's
threshold for program ``what`` on, in tiles (the ``"tiles"`` pass) where the policy says,
and the vmapped array program below it. Its derivative (`_dual_jvp`) differentiates the
program the call runs, so second derivatives of a batch run the batch's program. With
the passes off, a batch is JAX's ``vmap`` of the array program.
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
    _HAVE_LINEAR_CALL_BATCHING,
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

    ``settle``: how the derivative rule (`_dual_jvp`) starts the carry tangents of the
    programs' loops (``None``: as JAX finds them). ``columns``: for the ``jvp`` of a
    Jacobian program, where its columns are (`scalarized.columns_outside`).

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
    """`_dual`'s derivative (second derivatives of a run: its rule's programs differentiated).

    For the forward and Jacobian programs, the value is a `_dual` of the same
    programs (scalarized under a ``vmap`` of 16 runs or more, ``batched_layout``) and the
    tangent a ``linear_call`` (`_linear_tangent`) whose program is the ``jvp`` of the
    program `_dual` would run, itself a `_dual` (``"jvp"``): a batch's second
    derivatives run the batch's program, not the array program's. Integer outputs (a
    run's status) get their ``float0`` zeros outside the ``linear_call``. The other
    programs, and the ``"jvp"`` programs themselves (third derivatives): JAX's ``jvp``
    of the array program (`_array_jvp`).

    The ``linear_call``'s batching rule (`so3jax._engine.linear_call`) leaves a call with
    nothing batched unbatched: JAX calls it under every ``vmap`` in scope (the inner
    ``jacfwd``'s basis of ``jacfwd`` of ``jacfwd`` too), and batching its outputs there
    would batch this rule's value with its tangent.

    ``settle(primals, leaves, t_leaves, nz) -> (t_leaves, nz)`` (`_dual`'s; the Jacobian
    program's is the ``"settle"`` pass's `jacobian_tangents`) starts the loop's carry
    tangents that a step makes nonzero with zeros, so that JAX differentiates and batches
    each loop of the ``jvp`` programs once.
    """
    _plan.note("derivative", strategy="second derivative", program=what)
    if what not in ("run", "jacobian") or not _HAVE_LINEAR_CALL_BATCHING:
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
        in_cols, out_cols = scalarized.jacobian_columns(primals, jax.tree.structure(out))
        # the jvp program's arguments are (xs, ts, others): the differentiated leaves,
        # their tangents (shaped alike), and every leaf
        xs_cols = _pick(nz, in_cols)
        columns = (xs_cols + xs_cols + in_cols, _pick(out_nz, out_cols))
    fast = _dual(plain, _float_tangent(scalar_fn, treedef, nz, out_nz), "jvp", columns=columns)
    xs, ts = _pick(nz, leaves), _pick(nz, t_leaves)
    # The tangents the settle added are zeros (not real ones): `_linear_tangent`'s transpose.
    tan = _linear_tangent(plain, fast, xs, leaves, ts, _pick(nz, real))
    return out, _with_float0(out, out_nz, tan)


class _Traced:
    """A traced array program: called as it was traced, or batched with its loops settled.

    Under ``vmap``, a `lax.scan` whose carry starts partly unbatched finds which
    components become batched by batching its body again until nothing changes:
    two passes over the forward loop's body for the seed (the run's status
    starts unbatched), two over the Jacobian program's (its tangents start as
    unbatched zeros), each nested scan once more per pass. `vmap` walks
    the jaxpr's top-level equations; with the ``"settle"`` pass, before each loop it
    batches the carry components that its body would batch (`settle.batched_carries`:
    the same fixed point, on flags), so that JAX batches each body once. What stays
    unbatched (the reference attitude a batch shares) stays so. The scalarized programs
    do the same on their flat components (`sc.settle_batched`, part of ``"scalarize"``).
    """

    def __init__(self, closed, out_tree):
        self.closed, self.out_tree = closed, out_tree
        self.pending = None

    def __call__(self, *args):
        # The decisions of the unbatched program, which `custom_vmap` also traces when a
        # batch then runs its rule instead: `_dual` keeps them only for an unbatched call.
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
            index = cut_index(args) if cuts else None

            def runs(*args):
                if index is not None:  # the loops settle their carry's batching up front
                    # (`sc.settle_batched`)
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
