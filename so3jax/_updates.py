"""The group updates the integrators step with, and their derivative rules.

``R exp(w)``, ``R cay(u)`` and their increments ``R (exp(w) - I)``, ``R (cay(u) - I)``
(`so3jax._state` advances a state with them), each a ``jax.custom_jvp`` with its
closed-form rule, and a `so3jax._engine.passes.frames.Frame` rule (a three-number tangent ``xi`` in
``dR = R hat(xi)``) for the engine's scalarized Jacobian programs. This is where the
SO(3) formulas of `so3jax._so3` meet the execution engine: the values the engine's
CPU programs should materialize are marked here (`so3jax._engine.passes.cuts.array_cut`), so
that `so3jax._so3` itself stays pure maths and imports nothing from the engine.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from ._engine.passes.cuts import array_cut as _array_cut, array_cut_index as _array_cut_index
from ._engine.passes.frames import Frame, frame_rule, right_or_zero
from ._so3 import (
    _ab_coeffs,
    _abc_coeffs,
    _cay_increment_raw,
    _cross,
    _dot,
    _expm1_for_rules,
    _expm1_from,
    _expm1_raw,
    _eye_like,
    _mm,
    _right_jacobian_times,
    _times_expm1,
)
from ._types import Array


def _rmul_exp(R: Array, w: Array) -> Array:
    """``R exp(w)`` computed as ``R + R (exp(w) - I)``.

    For the small increments of a time step this keeps the rounding error of
    the update proportional to ``|w|``: forming ``exp(w)`` first would round
    its entries near 1 to ``eps`` each step, the same way every step when the
    rate is steady, so float32 runs would drift off the group linearly in time.
    """
    # Materialized (`so3jax._engine.passes.cuts.array_cut_index`): in a chain of updates (the
    # commutator-free methods) XLA would recompute each factor in every element
    # of the next.
    (out,) = _array_cut(_array_cut_index(w), _exp_update(R, w))
    return out


def _rmul_cay(R: Array, u: Array) -> Array:
    """``R cay(u)`` computed as ``R + R (cay(u) - I)``, with the Cayley map
    ``cay(u) = (I - hat(u)/2)^-1 (I + hat(u)/2) = I + 4 / (4 + |u|^2) (hat u + hat(u)^2 / 2)``.

    Exactly orthogonal like ``exp`` but rational: no trigonometric functions,
    square roots or small-angle branches. Rows of ``R hat(u)`` are ``r_i x u``.
    """
    return _cay_update(R, u)


@jax.custom_jvp
def _expm1(w: Array) -> Array:
    """``exp(w) - I = A hat(w) + B hat(w)^2``, accurate relative to ``|w|``.

    Its derivative ``exp(w) hat(J_r(w) dw)`` is given in closed form (see
    `_exp_increment_jvp`).
    """
    return _expm1_raw(w)


@_expm1.defjvp
def _expm1_jvp(primals, tangents):
    (w,), (dw,) = primals, tangents
    E, B, C = _expm1_for_rules(w)
    cut = _array_cut_index(w)  # XLA would recompute E in every element of a product
    (E,) = _array_cut(cut, E)
    (v,) = _array_cut(cut, _right_jacobian_times(w, dw, B, C))
    return E, _cross(E + _eye_like(w, w.shape[:-1]), v[..., None, :]).astype(E.dtype)


@jax.custom_jvp
def _exp_update(R: Array, w: Array) -> Array:
    """``R exp(w) = R + R (exp(w) - I)`` (as `_rmul_exp`, without its cut), with one
    derivative rule for the whole update (`_exp_update_jvp`).

    The Runge-Kutta-Munthe-Kaas stages and steps move with it (`so3jax._state.move`).
    """
    return R + _exp_increment_raw(R, w)


@functools.partial(_exp_update.defjvp, symbolic_zeros=True)
def _exp_update_jvp(primals, tangents):
    """``d[R exp(w)] = dR exp(w) + R exp(w) hat(J_r(w) dw)``.

    `_exp_increment_jvp` for the update itself: ``dR exp(w)`` is one product, where
    ``dR + d[R (exp(w) - I)]`` is a product and a sum, and the rows of
    ``R exp(w) hat(v)`` read the update's own value: fewer operations per tangent column
    and fewer kernels a step in the one-pass Jacobian.
    """
    R, w = primals
    dR, dw = tangents
    E1, B, C = _expm1_for_rules(w)
    cut = _array_cut_index(w)  # as in `_exp_increment_jvp`
    E, out = _array_cut(cut, E1 + _eye_like(w, w.shape[:-1]), R + _mm(R, E1))
    d = None
    if not isinstance(dR, SymbolicZero):
        d = _mm(dR, E)
    if not isinstance(dw, SymbolicZero):
        (v,) = _array_cut(cut, _right_jacobian_times(w, dw, B, C))
        rows = _cross(out, v[..., None, :])  # rows of R exp(w) hat(v) are r_i x v
        d = rows if d is None else d + rows
    if d is None:  # pragma: no cover (the rule runs only with a nonzero tangent)
        d = jnp.zeros_like(out)
    return out, jnp.broadcast_to(d, out.shape).astype(out.dtype)


def _frame_update(tR, tw, rotate, jacobian):
    """``xi'`` of an update ``R g(w)`` (``g`` orthogonal) from ``dR = R hat(xi)`` (``tR``, a
    right `Frame` or ``None``) and ``dw`` (``tw``): ``g^T xi + v``, ``R g hat(v)`` the
    update's tangent through ``w`` (``rotate(xi) = g^T xi``, ``jacobian(dw) = v``)."""
    if tR is None:
        return jacobian(tw)
    return rotate(tR.xi) if tw is None else rotate(tR.xi) + jacobian(tw)


@frame_rule(_exp_update)
def _exp_update_frame(xs, ts):
    """`_exp_update` with ``dR = R hat(xi)`` (`so3jax._engine.passes.frames`): ``R' = R exp(w)`` and
    ``xi' = exp(w)^T xi + J_r(w) dw = xi - A w x xi + B w x (w x xi) + J_r(w) dw``: about
    40 operations a column where ``dR exp(w) + R' hat(J_r(w) dw)`` takes 110."""
    (R, w), (tR, tw) = xs, ts
    return _exp_frame(R, w, tR, tw)


def _exp_frame(R, w, tR, tw):
    if not right_or_zero(tR):
        return None
    t = _dot(w, w)
    A, B, C = _abc_coeffs(t)
    cut = _array_cut_index(w)
    A, B, C, out = _array_cut(cut, A, B, C, R + _mm(R, _expm1_from(w, t, A, B)))

    def rotate(xi):  # exp(-w) xi
        wx = _cross(w, xi)
        return xi - A[..., None] * wx + B[..., None] * _cross(w, wx)

    xi = _frame_update(tR, tw, rotate, lambda v: _right_jacobian_times(w, v, B, C))
    return [out], [Frame(xi.astype(out.dtype))]


def _cay_update_frame(xs, ts):
    """`_cay_update` with ``dR = R hat(xi)``: ``xi' = cay(u)^T xi + c (du - u x du / 2)``,
    ``cay(u)^T xi = xi + c (u x (u x xi) / 2 - u x xi)``, ``c = 4 / (4 + |u|^2)``."""
    (R, u), (tR, tu) = xs, ts
    return _cay_frame(R, u, tR, tu)


def _cay_frame(R, u, tR, tu):
    if not right_or_zero(tR):
        return None
    cut = _array_cut_index(u)
    c = (4.0 / (4.0 + _dot(u, u)))[..., None]
    c, out = _array_cut(cut, c, R + _cay_increment_raw(R, u))

    def rotate(xi):
        ux = _cross(u, xi)
        return xi + c * (0.5 * _cross(u, ux) - ux)

    xi = _frame_update(tR, tu, rotate, lambda v: c * (v - 0.5 * _cross(u, v)))
    return [out], [Frame(xi.astype(out.dtype))]


@jax.custom_jvp
def _exp_increment(R: Array, w: Array) -> Array:
    """``R (exp(w) - I)``: the increment of `_rmul_exp`.

    Its derivative is given in closed form (`_exp_increment_jvp`) rather than
    left to autodiff of Rodrigues' formula.
    """
    return _exp_increment_raw(R, w)


def _exp_increment_raw(R: Array, w: Array) -> Array:
    return _times_expm1(R, w, *_ab_coeffs(_dot(w, w)))


@functools.partial(_exp_increment.defjvp, symbolic_zeros=True)
def _exp_increment_jvp(primals, tangents):
    """``d[R (exp(w) - I)] = dR (exp(w) - I) + R exp(w) hat(J_r(w) dw)``.

    From ``d/dt exp(w) = exp(w) hat(J_r(w) w')`` with ``J_r(w) v = v - B w x v
    + C w x (w x v)``. The same derivative as autodiff of `_expm1`, to
    round-off, at about a third of the operations: autodiff differentiates
    both branches of every small-angle ``where`` in the coefficients and the
    matrix product ``R (exp(w) - I)`` in full. This is what a tangent or
    adjoint step of an RKMK method spends most of its time on (an RKMK4 step
    has four exponentials).
    """
    R, w = primals
    dR, dw = tangents
    # Here exp(w) - I is formed once and multiplied, in fewer kernels than the primal's
    # row cross products would take (in the array layout the number of kernels sets
    # the time).
    E, B, C = _expm1_for_rules(w)
    # Materialized once (`so3jax._engine.passes.cuts.array_cut_index`): XLA would
    # otherwise recompute E and D, sines and cosines included, in every element of the
    # tangent products.
    cut = _array_cut_index(w)
    E, D = _array_cut(cut, E, _mm(R, E))
    dD = None
    if not isinstance(dR, SymbolicZero):
        dD = _mm(dR, E)
    if not isinstance(dw, SymbolicZero):
        (v,) = _array_cut(cut, _right_jacobian_times(w, dw, B, C))
        rows = _cross(R + D, v[..., None, :])  # rows of (R + D) hat(v) are r_i x v
        dD = rows if dD is None else dD + rows
    if dD is None:  # pragma: no cover (the rule runs only with a nonzero tangent)
        dD = jnp.zeros_like(D)
    return D, jnp.broadcast_to(dD, D.shape).astype(D.dtype)


@jax.custom_jvp
def _cay_update(R: Array, u: Array) -> Array:
    """``R cay(u) = R + R (cay(u) - I)`` with one derivative rule for the whole update
    (as `_exp_update`)."""
    return R + _cay_increment_raw(R, u)


frame_rule(_cay_update)(_cay_update_frame)


@functools.partial(_cay_update.defjvp, symbolic_zeros=True)
def _cay_update_jvp(primals, tangents):
    """``d[R cay(u)] = dR cay(u) + R cay(u) hat(c (du - u x du / 2))`` (see
    `_cay_increment_jvp`), with ``dR cay(u)`` one product (as `_exp_update_jvp`)."""
    R, u = primals
    dR, du = tangents
    cut = _array_cut_index(u)
    out = R + _cay_increment_raw(R, u)
    d = None
    if not isinstance(dR, SymbolicZero):
        eye = _eye_like(u, u.shape[:-1])
        K, out = _array_cut(cut, eye + _cay_increment_raw(eye, u), out)
        d = _mm(dR, K)
    if not isinstance(du, SymbolicZero):
        c = (4.0 / (4.0 + _dot(u, u)))[..., None]
        (v,) = _array_cut(cut, c * (du - 0.5 * _cross(u, du)))
        rows = _cross(out, v[..., None, :])
        d = rows if d is None else d + rows
    if d is None:  # pragma: no cover
        d = jnp.zeros_like(out)
    return out, jnp.broadcast_to(d, out.shape).astype(out.dtype)


@jax.custom_jvp
def _cay_increment(R: Array, u: Array) -> Array:
    """``R (cay(u) - I)``: the increment of `_rmul_cay` (derivative in closed form)."""
    return _cay_increment_raw(R, u)


@functools.partial(_cay_increment.defjvp, symbolic_zeros=True)
def _cay_increment_jvp(primals, tangents):
    """``d[R (cay(u) - I)] = dR (cay(u) - I) + R cay(u) hat(c (du - u x du / 2))``.

    ``c = 4 / (4 + |u|^2)``: the right-trivialised derivative of the Cayley map
    is the inverse of `_dcayinv`'s ``I + hat(u)/2 + u u^T/4``, which is
    ``c (I - hat(u)/2)``. About 2/3 of the operations of autodiff.
    """
    R, u = primals
    dR, du = tangents
    cut = _array_cut_index(u)  # as in `_exp_increment_jvp`
    D = _cay_increment_raw(R, u)
    dD = None
    if not isinstance(dR, SymbolicZero):
        K, D = _array_cut(cut, _cay_increment_raw(_eye_like(u, u.shape[:-1]), u), D)
        dD = _mm(dR, K)
    if not isinstance(du, SymbolicZero):
        c = (4.0 / (4.0 + _dot(u, u)))[..., None]
        (v,) = _array_cut(cut, c * (du - 0.5 * _cross(u, du)))
        rows = _cross(R + D, v[..., None, :])
        dD = rows if dD is None else dD + rows
    if dD is None:  # pragma: no cover
        dD = jnp.zeros_like(D)
    return D, jnp.broadcast_to(dD, D.shape).astype(D.dtype)
