"""States on the product manifold SO(3)^k x R^n, and their tangents."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from ._engine.passes.frames import Frame, frame_rule
from ._so3 import _cay_increment_raw
from ._types import Array, Float
from ._updates import (
    _cay_frame,
    _cay_increment,
    _cay_update,
    _cay_update_jvp,
    _exp_frame,
    _exp_increment,
    _exp_increment_raw,
    _exp_update,
    _exp_update_jvp,
)


class LieState(eqx.Module):
    """A point of ``SO(3)^k x R^n``: ``k`` stacked rotations and a flat vector.

    The free body is ``(R[None], Omega)``; a tracking scene is
    ``(stack([R, Rd]), Omega)``. Integrators move the rotations along the group
    (``R <- R exp(u)``) and the vector part additively.

    **Fields:**

    - `R`: rotations, shape `(..., k, 3, 3)`.
    - `x`: vector part, shape `(..., n)`.
    """

    R: Float[Array, "*batch k 3 3"]
    x: Float[Array, "*batch n"]


class LieTangent(eqx.Module):
    """A tangent vector in body (left-trivialised) form.

    **Fields:**

    - `xi`: body angular velocities of the rotations, shape `(..., k, 3)`
      (``R_i' = R_i hat(xi_i)``).
    - `dx`: derivative of the vector part, shape `(..., n)`.
    """

    xi: Float[Array, "*batch k 3"]
    dx: Float[Array, "*batch n"]


def retract(y: LieState, u: Array, dx: Array, coords: str = "exp") -> LieState:
    """``(R exp(u), x + dx)``: move along the group and in the vector part.

    ``coords="cayley"`` moves by the Cayley map, ``R cay(u)``, instead.
    """
    return LieState(move(y.R, u, coords), y.x + dx)


def move(R: Array, u: Array, coords: str = "exp") -> Array:
    """``R exp(u)`` (or ``R cay(u)``), computed as ``R + increment(R, u)``.

    Its derivative is one closed-form rule for the whole update (`so3jax._updates._exp_update`).
    """
    return (_cay_update if coords == "cayley" else _exp_update)(R, u)


def advance(y: LieState, u: Array, dx: Array, coords: str = "exp") -> LieState:
    """``(R exp(u), x + dx)``: `retract` for the end of a step.

    The same values and derivative rule (`move`'s); only the order in which a
    program computes them differs: ``R exp(u) - R``, then ``x + dx``, then the sum
    ``R + (R exp(u) - R)``, the order in which the scalarized forward programs
    were tuned (computed in `retract`'s order, the seed's batched forward pass
    over 256 runs took 1.02x to 1.06x longer: its fusion cuts group differently).
    """
    R1, x1 = _advance(y.R, u, y.x, dx, coords)
    return LieState(R1, x1)


def _advance(R, u, x, dx, coords):
    return (_advance_cay if coords == "cayley" else _advance_exp)(R, u, x, dx)


def _advance_value(R, u, x, dx, coords):
    D = (_cay_increment_raw if coords == "cayley" else _exp_increment_raw)(R, u)
    x1 = x + dx
    return R + D, x1


def _advance_jvp(coords, primals, tangents):
    R, u, x, dx = primals
    dR, du, dxx, ddx = tangents
    rule = _cay_update_jvp if coords == "cayley" else _exp_update_jvp
    if isinstance(dR, SymbolicZero) and isinstance(du, SymbolicZero):
        R1, dR1 = move(R, u, coords), jnp.zeros_like(R)
    else:
        R1, dR1 = rule((R, u), (dR, du))
    x1, dx1 = _sum_tangent(x, dx, [t for t in (dxx, ddx) if not isinstance(t, SymbolicZero)])
    return (R1, x1), (dR1, jnp.zeros_like(x1) if dx1 is None else dx1)


def _sum_tangent(x, dx, parts):
    x1 = x + dx
    if not parts:
        return x1, None
    return x1, jnp.broadcast_to(functools.reduce(jnp.add, parts), x1.shape).astype(x1.dtype)


def _advance_frame(coords, xs, ts):
    """`_advance` with ``dR = R hat(xi)`` (`so3jax._engine.passes.frames`): the update's
    `Frame` rule."""
    (R, u, x, dx), (tR, tu, tx, tdx) = xs, ts
    if any(isinstance(t, Frame) for t in (tu, tx, tdx)):
        return None
    res = (_cay_frame if coords == "cayley" else _exp_frame)(R, u, tR, tu)
    if res is None:
        return None
    (R1,), (fR,) = res
    x1, dx1 = _sum_tangent(x, dx, [t for t in (tx, tdx) if t is not None])
    return [R1, x1], [fR, dx1]


# One function per coordinates (a `Frame` rule finds them by name).
@jax.custom_jvp
def _advance_exp(R, u, x, dx):
    return _advance_value(R, u, x, dx, "exp")


@jax.custom_jvp
def _advance_cay(R, u, x, dx):
    return _advance_value(R, u, x, dx, "cayley")


_advance_exp.defjvp(functools.partial(_advance_jvp, "exp"), symbolic_zeros=True)
_advance_cay.defjvp(functools.partial(_advance_jvp, "cayley"), symbolic_zeros=True)
frame_rule(_advance_exp)(functools.partial(_advance_frame, "exp"))
frame_rule(_advance_cay)(functools.partial(_advance_frame, "cayley"))


def increment(R: Array, u: Array, coords: str = "exp") -> Array:
    """``R exp(u) - R`` (or ``R cay(u) - R``), computed without forming ``R exp(u)``."""
    return (_cay_increment if coords == "cayley" else _exp_increment)(R, u)


def all_finite(tree) -> Array:
    """A scalar bool: every leaf of ``tree`` is finite."""
    leaves = [jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(tree)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.array(True)
