"""A linear map with a custom transpose that also batches: so3jax's own primitive.

``linear_call(fun, fun_transpose, residual_args, linear_args)`` has the contract of
`jax.custom_derivatives.linear_call`: ``fun(res, lin)`` is linear in ``lin``,
``fun_transpose(res, ct)`` is its transpose, and the transpose of the call is a call of
``fun_transpose`` whose own transpose is ``fun``. JAX's primitive for it has no
batching rule, so ``vmap`` of a gradient through it raises. Rather than add a rule to
JAX's tables for JAX's primitive (which every program in the process would then run),
so3jax defines its own primitive, ``so3jax_linear_call``, and gives it the rules it
needs: evaluation and lowering (the callee's jaxpr), JVP (linear in ``lin``; residuals
are not differentiated), transpose (the call of ``fun_transpose``), and batching (the
callee and the transpose vmapped, linear inputs batched in front). This is the pattern
of equinox's `filter_primitive_*` helpers. Nothing here touches a primitive so3jax did
not define.

The rules use JAX's rule tables for a new primitive (`jax.interpreters.ad`,
`jax.interpreters.batching`, `jax.interpreters.mlir`) and `jax.extend.core`. Where one
of them is missing (a JAX release that moved them), `AVAILABLE` is False: the engine then
runs its reference programs (JAX's own autodiff) and warns once (`so3jax._engine`).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

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


def linear_call(fun: Callable, fun_transpose: Callable, residual_args, linear_args):
    """``fun(residual_args, linear_args)``, linear in ``linear_args``, transposed by
    ``fun_transpose(residual_args, cotangents)``; batches under ``vmap``.

    **Arguments:**

    - `fun`: ``(res, lin) -> out``, linear in ``lin`` (pytrees of arrays).
    - `fun_transpose`: ``(res, ct) -> lin_ct`` with ``ct`` shaped as ``out`` and
      ``lin_ct`` as ``lin``. Traced when a transpose is needed (lazily, as JAX's
      ``linear_call`` does): it should get what it needs from ``res``.
    - `residual_args`, `linear_args`: pytrees of arrays.

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

    out = _bind(flat_fun, res, lin, flat_transpose)
    return jax.tree.unflatten(out_tree[0], out)


def _bind(flat_fun: Callable, res: list, lin: list, transpose: Callable) -> list:
    """Trace ``flat_fun(*res, *lin)`` and bind it; values it closes over become
    leading constant operands (so the primitive holds no tracer of this trace)."""
    closed = jax.make_jaxpr(flat_fun)(*res, *lin)
    consts = list(closed.consts)
    return linear_call_p.bind(
        *consts,
        *res,
        *lin,
        jaxpr=closed.jaxpr,
        n_consts=len(consts),
        n_res=len(res),
        transpose=transpose,
    )


def _eval(jaxpr, consts, *args):
    return jaxpr_as_fun(ClosedJaxpr(jaxpr, list(consts)))(*args)


def _impl(*args, jaxpr, n_consts, n_res, transpose):
    del n_res, transpose
    return _eval(jaxpr, args[:n_consts], *args[n_consts:])


def _abstract_eval(*args, jaxpr, n_consts, n_res, transpose):
    del args, n_consts, n_res, transpose
    return [v.aval for v in jaxpr.outvars]


def _jvp(primals, tangents, *, jaxpr, n_consts, n_res, transpose):
    params = dict(jaxpr=jaxpr, n_consts=n_consts, n_res=n_res, transpose=transpose)
    n_pre = n_consts + n_res
    if not all(type(t) is ad.Zero for t in tangents[:n_pre]):
        raise NotImplementedError("linear_call does not differentiate its residuals")
    out = linear_call_p.bind(*primals, **params)
    lin_t = [ad.instantiate_zeros(t) for t in tangents[n_pre:]]
    return out, linear_call_p.bind(*primals[:n_pre], *lin_t, **params)


def _transpose(cts, *args, jaxpr, n_consts, n_res, transpose):
    consts, res, lin = args[:n_consts], args[n_consts : n_consts + n_res], args[n_consts + n_res :]
    if not all(ad.is_undefined_primal(x) for x in lin) or any(
        ad.is_undefined_primal(x) for x in (*consts, *res)
    ):
        raise NotImplementedError("linear_call transposes in its linear inputs only")
    cts = [
        jnp.zeros(v.aval.shape, v.aval.dtype) if type(ct) is ad.Zero else ct
        for ct, v in zip(cts, jaxpr.outvars, strict=True)
    ]
    res = list(res)

    def back(res_leaves, ct_leaves):  # the transpose's transpose: the callee itself
        return _eval(jaxpr, consts, *res_leaves, *ct_leaves)

    out = _bind(lambda *a: transpose(list(a[:n_res]), list(a[n_res:])), res, cts, back)
    return [None] * (n_consts + n_res) + list(out)


def _batch(args, dims, *, jaxpr, n_consts, n_res, transpose):
    params = dict(jaxpr=jaxpr, n_consts=n_consts, n_res=n_res, transpose=transpose)
    n_out = len(jaxpr.outvars)
    if all(d is None for d in dims):
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

    out = _bind(batched, pre, lin, batched_transpose)
    return out, [0] * n_out


if AVAILABLE:
    linear_call_p = Primitive("so3jax_linear_call")
    linear_call_p.multiple_results = True
    linear_call_p.def_impl(_impl)
    linear_call_p.def_abstract_eval(_abstract_eval)
    ad.primitive_jvps[linear_call_p] = _jvp
    ad.primitive_transposes[linear_call_p] = _transpose
    batching.primitive_batchers[linear_call_p] = _batch
    mlir.register_lowering(linear_call_p, mlir.lower_fun(_impl, multiple_results=True))
