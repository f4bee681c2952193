"""A linear map with a custom transpose that also batches: so3jax's own primitive.

``linear_call(fun, fun_transpose, residual_args, linear_args)`` has the contract of
`jax.custom_derivatives.linear_call`, whose primitive has no batching rule. so3jax's own,
``so3jax_linear_call``, has evaluation and lowering (the callee's jaxpr), JVP, transpose (a
call of ``fun_transpose``, whose own transpose is ``fun``) and batching rules, as equinox's
`filter_primitive_*` helpers do; nothing is registered for a primitive so3jax did not define
(docs/engine.md, "so3jax's own linear_call"; tests/test_linear_call.py).

`AVAILABLE` is False where JAX lacks the rule tables (`jax.interpreters.ad`, ``batching``,
``mlir``, `jax.extend.core`): the engine then runs its reference programs and warns once.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from .trees import _spec

try:  # the public rule tables for a primitive of one's own
    from jax.extend.core import ClosedJaxpr, Primitive, jaxpr_as_fun
    from jax.interpreters import ad, batching, mlir

    AVAILABLE = all(
        hasattr(m, n)
        for m, n in [
            (ad, "primitive_jvps"),
            (ad, "primitive_transposes"),
            (ad, "Zero"),
            (ad, "is_undefined_primal"),
            (ad, "instantiate_zeros"),
            (batching, "primitive_batchers"),
            (mlir, "register_lowering"),
            (mlir, "lower_fun"),
        ]
    )
except ImportError:  # pragma: no cover - JAX moved them
    AVAILABLE = False

__all__ = ["AVAILABLE", "linear_call"]


def linear_call(
    fun: Callable,
    fun_transpose: Callable,
    residual_args,
    linear_args,
    symbolic_zeros=False,
    differentiable: Callable | None = None,
    out_shapes=None,
):
    """``fun(residual_args, linear_args)``, linear in ``linear_args``, transposed by
    ``fun_transpose(residual_args, cotangents)``; batches under ``vmap``.

    **Arguments:**

    - `fun`: ``(res, lin) -> out``, linear in ``lin`` (pytrees of arrays).
    - `fun_transpose`: ``(res, ct) -> lin_ct``, ``ct`` shaped as ``out`` and ``lin_ct`` as
      ``lin`` (`TypeError` otherwise). Traced lazily, when a transpose is needed: it should
      take what it needs from ``res``.
    - `residual_args`, `linear_args`: pytrees of arrays.
    - `symbolic_zeros`: if true, ``fun_transpose`` gets ``None`` for each cotangent leaf
      that is a symbolic zero (an unused output), else zeros.
    - `differentiable`: ``(res, lin) -> out``, ``fun`` in operations JAX differentiates and
      batches itself, for second derivatives (of the call or its transpose) where the
      residuals move. Default: ``fun`` as traced.
    - `out_shapes`: ``fun``'s output leaves (``jax.ShapeDtypeStruct`` or arrays), in its
      structure. Given, ``fun`` is traced only when the call is evaluated, lowered or
      differentiated again, never by reverse mode alone; a wrong shape, or ``fun`` closing
      over a traced value, then raises `ValueError`.

    **Returns:** ``fun(residual_args, linear_args)``.
    """
    if not AVAILABLE:  # pragma: no cover - exercised with the gate monkeypatched
        return jax.custom_derivatives.linear_call(fun, fun_transpose, residual_args, linear_args)
    res, res_tree = jax.tree.flatten(residual_args)
    lin, lin_tree = jax.tree.flatten(linear_args)
    n_res = len(res)
    out_tree = []

    def flat_fun(*args):
        out = fun(
            jax.tree.unflatten(res_tree, args[:n_res]), jax.tree.unflatten(lin_tree, args[n_res:])
        )
        leaves, tree = jax.tree.flatten(out)
        out_tree.append(tree)
        return leaves

    def flat_transpose(res_leaves, ct_leaves):
        ct = jax.tree.unflatten(out_tree[0], ct_leaves)
        lin_ct = fun_transpose(jax.tree.unflatten(res_tree, res_leaves), ct)
        leaves, tree = jax.tree.flatten(lin_ct)
        if tree != lin_tree:
            raise TypeError(
                "linear_call: the transpose's output must have the structure of the linear "
                f"inputs {lin_tree}, got {tree}"
            )
        return leaves

    flat_diff = None
    if differentiable is not None:

        def flat_diff(*args):
            out = differentiable(
                jax.tree.unflatten(res_tree, args[:n_res]),
                jax.tree.unflatten(lin_tree, args[n_res:]),
            )
            return jax.tree.leaves(out)

    flat_transpose.symbolic_zeros = bool(symbolic_zeros)
    if out_shapes is None:
        out = _bind(flat_fun, res, lin, flat_transpose, flat_diff)
        return jax.tree.unflatten(out_tree[0], out)
    shapes, tree = jax.tree.flatten(out_shapes)
    out_tree.append(tree)
    callee = _Callee(None, flat_fun, [_spec(x) for x in (*res, *lin)], [_spec(x) for x in shapes])
    out = _bind_callee(callee, [], res, lin, flat_transpose, flat_diff)
    return jax.tree.unflatten(tree, out)


class _Callee:
    """The callee of a call: a jaxpr traced where the call is bound, or a function traced at
    its first use (`linear_call`'s ``out_shapes``) whose output shapes are given."""

    def __init__(self, jaxpr, fn=None, in_avals=(), out_avals=()):
        self._jaxpr, self._fn, self._in_avals = jaxpr, fn, in_avals
        self._consts: list = []
        self.out_avals = (
            [jax.typeof(a) for a in out_avals] if jaxpr is None else [v.aval for v in jaxpr.outvars]
        )

    @property
    def lazy(self) -> bool:
        """Whether the callee is still to be traced."""
        return self._jaxpr is None

    def closed(self, consts) -> ClosedJaxpr:
        """The callee with ``consts`` (the call's constant operands), or its own if traced
        late (it closes over no traced value: none to pass)."""
        if self._jaxpr is None:
            closed = jax.make_jaxpr(self._fn)(*self._in_avals)
            if any(isinstance(c, jax.core.Tracer) for c in closed.consts):
                raise ValueError(
                    "linear_call: with out_shapes, fun must not close over a traced value"
                )
            got = [(v.aval.shape, v.aval.dtype) for v in closed.jaxpr.outvars]
            if got != [(a.shape, a.dtype) for a in self.out_avals]:
                raise ValueError(f"linear_call: fun's output {got} is not out_shapes")
            self._jaxpr, self._consts = closed.jaxpr, list(closed.consts)
        return ClosedJaxpr(self._jaxpr, list(consts) or self._consts)


def _bind(flat_fun: Callable, res: list, lin: list, transpose: Callable, diff=None) -> list:
    """Trace ``flat_fun(*res, *lin)`` and bind it; closed-over values become leading constant
    operands (no tracer of this trace in the primitive). ``diff``: `linear_call`'s
    ``differentiable``, dropped where it closes over a traced value."""
    closed = jax.make_jaxpr(flat_fun)(*res, *lin)
    return _bind_callee(_Callee(closed.jaxpr), list(closed.consts), res, lin, transpose, diff)


def _bind_callee(callee: _Callee, consts: list, res: list, lin: list, transpose, diff) -> list:
    if diff is not None and any(isinstance(c, jax.core.Tracer) for c in consts):
        diff = None
    return linear_call_p.bind(
        *consts,
        *res,
        *lin,
        jaxpr=callee,
        n_consts=len(consts),
        n_res=len(res),
        transpose=transpose,
        diff=diff,
    )


def _eval(callee: _Callee, consts, *args):
    return jaxpr_as_fun(callee.closed(consts))(*args)


def _impl(*args, jaxpr, n_consts, n_res, transpose, diff):
    del n_res, transpose, diff
    return _eval(jaxpr, args[:n_consts], *args[n_consts:])


def _abstract_eval(*args, jaxpr, n_consts, n_res, transpose, diff):
    del args, n_consts, n_res, transpose, diff
    return jaxpr.out_avals


def _jvp(primals, tangents, *, jaxpr, n_consts, n_res, transpose, diff):
    params = dict(jaxpr=jaxpr, n_consts=n_consts, n_res=n_res, transpose=transpose, diff=diff)
    n_pre = n_consts + n_res
    if not all(type(t) is ad.Zero for t in tangents[:n_pre]):
        # moved residuals (a second derivative): JAX's jvp of ``diff``, else of the callee
        nz = [type(t) is not ad.Zero for t in tangents]
        xs = [p for p, z in zip(primals, nz, strict=True) if z]
        use_diff = diff is not None and not any(nz[:n_consts])

        def g(*xs):
            it = iter(xs)
            args = [next(it) if z else p for p, z in zip(primals, nz, strict=True)]
            if use_diff:
                return diff(*args[n_consts:])
            return _eval(jaxpr, args[:n_consts], *args[n_consts:])

        ts = [t for t in tangents if type(t) is not ad.Zero]
        return jax.jvp(g, xs, ts)
    out = linear_call_p.bind(*primals, **params)
    lin_t = [ad.instantiate_zeros(t) for t in tangents[n_pre:]]
    return out, linear_call_p.bind(*primals[:n_pre], *lin_t, **params)


def _transpose(cts, *args, jaxpr, n_consts, n_res, transpose, diff):
    consts, res, lin = args[:n_consts], args[n_consts : n_consts + n_res], args[n_consts + n_res :]
    if not all(ad.is_undefined_primal(x) for x in lin) or any(
        ad.is_undefined_primal(x) for x in (*consts, *res)
    ):
        raise NotImplementedError("linear_call transposes in its linear inputs only")
    zero = [type(ct) is ad.Zero for ct in cts]
    if not getattr(transpose, "symbolic_zeros", False):
        cts = [
            jnp.zeros(v.shape, v.dtype) if z else ct
            for ct, z, v in zip(cts, zero, jaxpr.out_avals, strict=True)
        ]
        zero = [False] * len(cts)
    res = list(res)

    def with_nones(given):  # every output's cotangent: None for the symbolic zeros
        it = iter(given)
        return [None if z else next(it) for z in zero]

    def back(res_leaves, ct_leaves):  # the transpose's transpose: the callee itself
        outs = _eval(jaxpr, consts, *res_leaves, *ct_leaves)
        return [o for o, z in zip(outs, zero, strict=True) if not z]

    def call(*a):
        return transpose(list(a[:n_res]), with_nones(a[n_res:]))

    given = [ct for ct, z in zip(cts, zero, strict=True) if not z]
    t_diff = None
    if diff is not None:
        lin_avals = [x.aval for x in lin]
        out_avals = jaxpr.out_avals

        def t_diff(*a):  # JAX's transpose of ``diff``, linear in its last arguments
            res_leaves, full = list(a[:n_res]), with_nones(a[n_res:])
            zeros = [jnp.zeros(v.shape, v.dtype) for v in lin_avals]
            _, pull = jax.vjp(lambda *lin: diff(*res_leaves, *lin), *zeros)
            full = [
                jnp.zeros(v.shape, v.dtype) if c is None else c
                for c, v in zip(full, out_avals, strict=True)
            ]
            return list(pull(full))

    out = _bind(call, res, given, back, t_diff)
    return [None] * (n_consts + n_res) + list(out)


def _batch(args, dims, *, jaxpr, n_consts, n_res, transpose, diff):
    params = dict(jaxpr=jaxpr, n_consts=n_consts, n_res=n_res, transpose=transpose, diff=diff)
    n_out = len(jaxpr.out_avals)
    if all(d is None for d in dims):  # left unbatched: docs/engine.md, "so3jax's own linear_call"
        return linear_call_p.bind(*args, **params), [None] * n_out
    size = next(a.shape[d] for a, d in zip(args, dims, strict=True) if d is not None)
    n_pre = n_consts + n_res
    front = [x if d is None else jnp.moveaxis(x, d, 0) for x, d in zip(args, dims, strict=True)]
    pre, lin = front[:n_pre], front[n_pre:]
    pre_axes = [None if d is None else 0 for d in dims[:n_pre]]
    lin = [
        x if d is not None else jnp.broadcast_to(x, (size, *jnp.shape(x)))
        for x, d in zip(lin, dims[n_pre:], strict=True)
    ]
    res_axes = pre_axes[n_consts:]

    batched = jax.vmap(lambda *a: _impl(*a, **params), in_axes=(*pre_axes, *[0] * len(lin)))

    def batched_transpose(pre_leaves, ct_leaves):
        res_leaves = pre_leaves[n_consts:]
        return jax.vmap(transpose, in_axes=(res_axes, 0))(res_leaves, ct_leaves)

    batched_transpose.symbolic_zeros = getattr(transpose, "symbolic_zeros", False)
    b_diff = None
    if diff is not None and all(d is None for d in dims[:n_consts]):
        b_diff = jax.vmap(diff, in_axes=(*res_axes, *[0] * len(lin)))
        b_diff = _dropping_consts(b_diff, n_consts)
    if jaxpr.lazy:  # still traced at its first use, batched
        outs = [jax.ShapeDtypeStruct((size, *a.shape), a.dtype) for a in jaxpr.out_avals]
        callee = _Callee(None, batched, [_spec(x) for x in (*pre, *lin)], outs)
        return _bind_callee(callee, [], pre, lin, batched_transpose, b_diff), [0] * n_out
    out = _bind(batched, pre, lin, batched_transpose, b_diff)
    return out, [0] * n_out


def _dropping_consts(fn: Callable, n_consts: int) -> Callable:
    """``fn(*res, *lin)`` called as ``g(*consts, *res, *lin)`` (``fn`` closes over the
    batched call's unbatched constants)."""
    return lambda *a: fn(*a[n_consts:])


if AVAILABLE:
    linear_call_p = Primitive("so3jax_linear_call")
    linear_call_p.multiple_results = True
    linear_call_p.def_impl(_impl)
    linear_call_p.def_abstract_eval(_abstract_eval)
    ad.primitive_jvps[linear_call_p] = _jvp
    ad.primitive_transposes[linear_call_p] = _transpose
    batching.primitive_batchers[linear_call_p] = _batch
    mlir.register_lowering(linear_call_p, mlir.lower_fun(_impl, multiple_results=True))
