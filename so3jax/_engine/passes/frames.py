"""The ``"frames"`` pass: attitude tangents as three numbers in the Jacobian programs.

Program in, program out: `frame_jvp` is ``jax.jvp`` of a function's jaxpr with `Frame` input
tangents, ``xi`` for ``R hat(xi)``: three numbers where JAX carries nine (docs/engine.md,
"Attitude tangents as three numbers"). Shape operations move a `Frame` (`_moved`), custom-JVP
functions with a `frame_rule` (in `so3jax._updates`, `_state`, `_control`, `_tune`) take and
give them, anything else gets the dense tangent and JAX's rule. The rules are exact
identities: tangents equal JAX's to round-off, ``tests/test_frames.py`` (rules),
``tests/passes/test_pass_frames.py`` (programs). Speed: ``benchmarks/ablation.py``.
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jex_core

from ..._so3 import _cross, _mm, _mT, _vee
from ..policy import current
from ..trees import _floats
from . import cuts

__all__ = ["Frame", "FrameError", "frame_jvp", "frame_rule", "dense", "right_or_zero"]


@dataclasses.dataclass(frozen=True)
class Frame:
    """The tangent ``P hat(xi)`` (``left``: ``hat(xi) P``) of a primal ``P`` of shape
    ``(..., 3, 3)``; ``xi`` has shape ``(..., 3)``."""

    xi: jax.Array
    left: bool = False


def right_or_zero(t) -> bool:
    """Whether ``t`` is a right `Frame` or zero (``None``): what rules take for a rotation."""
    return t is None or (isinstance(t, Frame) and not t.left)


class FrameError(ValueError):
    """An output asked for as a `Frame` came out dense; ``indices`` says which."""

    def __init__(self, indices):
        super().__init__(f"outputs {indices} have dense tangents")
        self.indices = tuple(indices)


#: custom-JVP function (by `_source_of`) -> rule ``(xs, ts) -> (outs, touts)``, or ``None``
#: for tangents it does not take (densified). ``ts`` entries: ``None`` (zero), array, `Frame`.
_RULES: dict[str, Callable] = {}
_DEBUG: list | None = None  # equations that densified a `Frame` (a test hook)


def _source_of(fn) -> str:
    """``"name at file:line"`` of ``fn``: its rule's key, as JAX records it (`_called`)."""
    f = inspect.unwrap(getattr(fn, "fun", fn))
    code = f.__code__
    return f"{f.__name__} at {code.co_filename}:{code.co_firstlineno}"


def frame_rule(fn):
    """Register the `Frame` rule of the custom-JVP function ``fn`` (a ``jax.custom_jvp``)."""
    key = _source_of(fn)

    def register(rule):
        _RULES[key] = rule
        return rule

    return register


def dense(P, t):
    """The tangent ``t`` of ``P`` as an array (``None`` stays ``None``)."""
    if not isinstance(t, Frame):
        return t
    xi = t.xi.astype(jnp.result_type(P))
    if t.left:  # columns of hat(xi) P are xi x p_j
        return jnp.swapaxes(_cross(xi[..., None, :], jnp.swapaxes(P, -1, -2)), -1, -2)
    return _cross(P, xi[..., None, :])  # rows of P hat(xi) are p_i x xi


def _called(eqn) -> str | None:
    """Where the function behind a ``custom_jvp_call`` equation is defined (`_source_of`)."""
    info = getattr(eqn.params.get("call_jaxpr"), "jaxpr", None)
    info = getattr(info, "debug_info", None)
    return getattr(info, "func_src_info", None)


def _is_float(aval) -> bool:
    return jnp.issubdtype(aval.dtype, jnp.inexact)


# Shape operations on the leading axes


def _keeps_matrix(in_shape, out_shape) -> bool:
    return tuple(in_shape[-2:]) == (3, 3) and tuple(out_shape[-2:]) == (3, 3)


def _moved(eqn, xs, ts, uniform):
    """A `Frame` through a shape operation on the leading axes, or ``None``."""
    name, p = eqn.primitive.name, eqn.params
    out_aval = eqn.outvars[0].aval
    frames = [t for t in ts if isinstance(t, Frame)]
    left = frames[0].left
    if any(t.left != left for t in frames):
        return None
    if any(t is not None and not isinstance(t, Frame) for t in ts):
        return None  # a dense tangent beside a frame
    x0 = xs[[i for i, t in enumerate(ts) if isinstance(t, Frame)][0]]
    in_shape = jnp.shape(x0)
    if not _keeps_matrix(in_shape, out_aval.shape):
        return None
    r = len(out_aval.shape)

    def xi_of(x, t):
        if t is None:
            return np.zeros(jnp.shape(x)[:-1], jnp.result_type(x))
        return t.xi

    if name in ("copy", "copy_p", "neg"):
        return Frame(ts[0].xi, left)
    if name == "convert_element_type":
        return Frame(ts[0].xi.astype(out_aval.dtype), left)
    # Below, a matrix's axes (..., 3, 3) map to its frame's (..., 3): leading axes unchanged.
    if name == "slice":
        start, limit, strides = p["start_indices"], p["limit_indices"], p["strides"]
        if tuple(start[-2:]) != (0, 0) or tuple(limit[-2:]) != (3, 3):
            return None
        if strides is not None and tuple(strides[-2:]) != (1, 1):
            return None
        strides = None if strides is None else tuple(strides[:-2]) + (1,)
        xi = jax.lax.slice(ts[0].xi, tuple(start[:-2]) + (0,), tuple(limit[:-2]) + (3,), strides)
        return Frame(xi, left)
    if name == "squeeze":
        dims = tuple(d % len(in_shape) for d in p["dimensions"])
        if any(d >= len(in_shape) - 2 for d in dims):
            return None
        return Frame(jax.lax.squeeze(ts[0].xi, dims), left)
    if name == "reshape":
        if p.get("dimensions") is not None:
            return None
        return Frame(jnp.reshape(ts[0].xi, tuple(p["new_sizes"][:-2]) + (3,)), left)
    if name == "broadcast_in_dim":
        bd = tuple(p["broadcast_dimensions"])
        if bd[-2:] != (r - 2, r - 1):
            return None
        shape = tuple(out_aval.shape[:-2]) + (3,)
        xi = jax.lax.broadcast_in_dim(ts[0].xi, shape, bd[:-2] + (r - 2,))
        return Frame(xi, left)
    if name == "concatenate":
        if p["dimension"] >= r - 2:
            return None
        xis = [xi_of(x, t) for x, t in zip(xs, ts, strict=True)]
        return Frame(jax.lax.concatenate(xis, p["dimension"]), left)
    if name == "stack":
        if p["axis"] % r >= r - 2:
            return None
        xis = [xi_of(x, t) for x, t in zip(xs, ts, strict=True)]
        return Frame(jnp.stack(xis, p["axis"] % r), left)
    if name == "select_n":
        pred = xs[0]
        if isinstance(eqn.invars[0], jex_core.Var) and eqn.invars[0] in uniform:
            pred = pred[..., 0, :]
        elif jnp.ndim(pred) != 0:
            return None
        xis = [xi_of(x, t) for x, t in zip(xs[1:], ts[1:], strict=True)]
        return Frame(jax.lax.select_n(pred, *xis), left)
    if name == "transpose":
        perm = tuple(p["permutation"])
        if perm[-2:] != (r - 1, r - 2) or perm[:-2] != tuple(range(r - 2)):
            return None
        return Frame(-ts[0].xi, not left)
    return None


_MOVES = frozenset(
    "copy copy_p neg convert_element_type slice squeeze reshape broadcast_in_dim concatenate "
    "select_n stack transpose".split()
)


# The interpreter


def _jvp_eqn(eqn, xs, ts):
    """JAX's ``jvp`` of one equation through the inputs with a (dense) tangent."""
    idx = [i for i, t in enumerate(ts) if t is not None]

    def f(*nz):
        args = list(xs)
        for i, a in zip(idx, nz, strict=True):
            args[i] = a
        return cuts._bind(eqn, args)

    outs, touts = jax.jvp(f, [xs[i] for i in idx], [ts[i] for i in idx])
    touts = [t if _is_float(v.aval) else None for t, v in zip(touts, eqn.outvars, strict=True)]
    return list(outs), touts


def _eval(jaxpr, consts, primals, tangents):
    env: dict = dict(zip(jaxpr.constvars, consts, strict=True))
    tan: dict = {}
    env.update(zip(jaxpr.invars, primals, strict=True))
    tan.update(zip(jaxpr.invars, tangents, strict=True))
    uniform: set = set()  # boolean values the same across a matrix's last two axes
    dense_of: dict = {}  # a Frame's dense tangent, formed once per value

    def read(v):
        if isinstance(v, jex_core.Literal):
            return v.val, None
        return env[v], tan.get(v)

    def densified(v, x, t):
        if not isinstance(t, Frame):
            return t
        if isinstance(v, jex_core.Literal) or v not in dense_of:
            d = dense(x, t)
            if not isinstance(v, jex_core.Literal):
                dense_of[v] = d
            return d
        return dense_of[v]

    for eqn in jaxpr.eqns:
        pairs = [read(v) for v in eqn.invars]
        xs, ts = [x for x, _ in pairs], [t for _, t in pairs]
        name = eqn.primitive.name
        floats_out = [_is_float(v.aval) for v in eqn.outvars]
        with eqn.ctx.manager:
            if all(t is None for t in ts) or not any(floats_out):
                outs, touts = cuts._bind(eqn, xs), [None] * len(eqn.outvars)
                if name == "broadcast_in_dim" and _uniform_broadcast(eqn):
                    uniform.add(eqn.outvars[0])
            else:
                outs = touts = None
                if any(isinstance(t, Frame) for t in ts):
                    outs, touts = _frame_eqn(eqn, xs, ts, uniform)
                if outs is None:
                    if _DEBUG is not None and any(isinstance(t, Frame) for t in ts):
                        _DEBUG.append(eqn)
                    ts = [densified(v, x, t) for v, x, t in zip(eqn.invars, xs, ts, strict=True)]
                    outs, touts = _jvp_eqn(eqn, xs, ts)
        for v, o, t in zip(eqn.outvars, outs, touts, strict=True):
            if not isinstance(v, jex_core.DropVar):
                env[v], tan[v] = o, t
    return [read(v) for v in jaxpr.outvars]


def _uniform_broadcast(eqn) -> bool:
    """A boolean broadcast whose value does not vary along the last two axes."""
    r = len(eqn.outvars[0].aval.shape)
    if r < 2 or eqn.outvars[0].aval.dtype != jnp.bool_:
        return False
    bd = eqn.params["broadcast_dimensions"]
    return r - 2 not in bd and r - 1 not in bd


def _frame_eqn(eqn, xs, ts, uniform):
    """``(outs, touts)`` for an equation with a `Frame` input, or ``(None, None)``."""
    name = eqn.primitive.name
    if name in _MOVES:
        t = _moved(eqn, xs, ts, uniform)
        if t is None:
            return None, None
        return cuts._bind(eqn, xs), [t]
    if name in ("pjit", "jit", "closed_call", "core_call"):
        inner = eqn.params.get("jaxpr") or eqn.params.get("call_jaxpr")
        if isinstance(inner, jex_core.ClosedJaxpr):
            res = _eval(inner.jaxpr, inner.consts, xs, ts)
            return [o for o, _ in res], [t for _, t in res]
        return None, None
    if name == "custom_jvp_call":
        rule = _RULES.get(_called(eqn))
        k = eqn.params["num_consts"]
        if rule is None or any(t is not None for t in ts[:k]):
            return None, None
        res = rule(xs[k:], ts[k:])
        if res is None:
            return None, None
        return list(res[0]), list(res[1])
    if name == "cond" and cuts._is_cut(eqn.params["branches"]):
        # A fusion cut without dense tangents: frames pass beside it (operand i+1 -> output i).
        if any(t is not None and not isinstance(t, Frame) for t in ts):
            return None, None
        return cuts._bind(eqn, xs), list(ts[1:])
    return None, None


def frame_jvp(fn: Callable, primals: list, tangents: list) -> tuple[list, list]:
    """``jax.jvp`` of ``fn`` (a list of arrays in, a list out) with `Frame` tangents
    allowed in ``tangents`` (``None``: zero). Returns the outputs and their tangents
    (``None``, an array or a `Frame`)."""
    closed = jax.make_jaxpr(fn)(*primals)
    res = _eval(closed.jaxpr, closed.consts, list(primals), list(tangents))
    return [o for o, _ in res], [t for _, t in res]


# The Jacobian programs' carry and observations with `Frame` tangents


#: A carry mask's flag: the leaf's tangent is carried as `Frame` ``xi`` (``dR = R hat(xi)``).
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
    return [dense(R, Frame(d)) if f else d for R, d, f in zip(cm, dc, fr, strict=True)]


def _jvp_with_frames(fn, Pm, cm, dP, dc, fr):
    """`frame_jvp` of ``fn(Pm, cm)`` (a pytree out), the carry tangents flagged in ``fr``
    given as `Frame` ``xi``: ``(out leaves, their tangents, out treedef)``."""
    tree = []

    def flat(*args):
        leaves, treedef = jax.tree.flatten(fn(list(args[: len(Pm)]), list(args[len(Pm) :])))
        tree.append(treedef)
        return leaves

    tin = list(dP) + [Frame(d) if f else d for d, f in zip(dc, fr, strict=True)]
    outs, touts = frame_jvp(flat, list(Pm) + list(cm), tin)
    return outs, touts, tree[-1]


def _frame_step(g, Pm, cm, dP, dc, fr):
    """``(dc1, c1)``: `Programs.tangent_step`'s ``jvp`` of ``g`` (``-> (masked carry floats,
    c1)``) with `Frame` carry tangents. Raises `FrameError` naming leaves that came out dense."""
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
            dc1.append(jnp.zeros_like(o) if t is None else dense(o, t))
    if bad:
        raise FrameError(bad)
    return dc1, jax.tree.unflatten(treedef, outs)[1]


#: An observation's kind in the Jacobian programs (`Programs.obs_kinds`): no tangent (zeros
#: outside), dense, or a `Frame` ``xi`` (right, left) that `_jacobian_jvp` densifies after the loop.
OBS_ZERO, OBS_DENSE, OBS_RIGHT, OBS_LEFT = 0, 1, 2, 3
#: The kinds as `so3jax.explain`'s plan names them (``"observations"`` entries).
OBS_NAMES = {OBS_ZERO: "none", OBS_DENSE: "dense", OBS_RIGHT: "right frame", OBS_LEFT: "left frame"}


def _obs_kind(x, t) -> int:
    """The kind of an observation ``x`` whose tangent `frame_jvp` gave as ``t``."""
    if t is None:
        return OBS_ZERO
    if current().on("frames") and isinstance(t, Frame):
        return OBS_LEFT if t.left else OBS_RIGHT
    return OBS_DENSE


def _obs_tangent(x, t, kind: int):
    """The tangent ``t`` of the observation ``x`` as its ``kind`` stores it: dense, or ``xi``
    (from a dense ``dR``: ``vee(R^T dR)`` or ``vee(dR R^T)``, exact for a rotation ``R``)."""
    if kind == OBS_DENSE:
        return jnp.zeros_like(x) if t is None else dense(x, t)
    left = kind == OBS_LEFT
    if t is None:
        return jnp.zeros(jnp.shape(x)[:-2] + (3,), jnp.result_type(x))
    if isinstance(t, Frame) and t.left == left:
        return t.xi.astype(jnp.result_type(x))
    d = dense(x, t)
    return _vee(_mm(d, _mT(x)) if left else _mm(_mT(x), d))


def _with_frames(mc, c0, nz_c) -> tuple:
    """``mc`` with `FRAME` for each masked carry leaf that may carry a `Frame`: rotation-
    shaped, without an input tangent (zero, ``R hat(0)``). `scalarized.jacobian` falls back to
    nine numbers where a step makes it dense (LGVI); the array layout always carries nine."""
    return tuple(
        FRAME
        if current().on("frames") and m and not z and tuple(jnp.shape(x)[-2:]) == (3, 3)
        else m
        for m, x, z in zip(mc, _floats(c0), nz_c, strict=True)
    )


def _frame_dense(R, xi, left: bool):
    """``dense(R, Frame(xi, left))`` by splits and concatenations only, so that its transpose
    has no reduction or pad: ``tests/test_engine.py::test_frame_dense_and_its_transpose``."""
    if left:  # hat(xi) R = -(R^T hat(xi))^T
        return -jnp.swapaxes(_frame_dense(jnp.swapaxes(R, -1, -2), xi, False), -1, -2)
    X = jnp.concatenate([xi[..., None, :].astype(R.dtype)] * 3, axis=-2)
    r0, r1, r2 = jnp.split(R, 3, axis=-1)
    x0, x1, x2 = jnp.split(X, 3, axis=-1)  # rows of R hat(xi) are r_i x xi
    return jnp.concatenate([r1 * x2 - r2 * x1, r2 * x0 - r0 * x2, r0 * x1 - r1 * x0], axis=-1)
