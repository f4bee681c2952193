"""The Lie group variational integrator of Lee, Leok & McClamroch.

Discrete Lagrange–d'Alembert equations of the rigid body with a torque ``M``:

    h hat(Pi_k + h/2 M_k) = F_k J_d - J_d F_k^T,     J_d = 1/2 tr(J) I - J
    R_{k+1} = R_k F_k
    Pi_{k+1} = F_k^T (Pi_k + h/2 M_k) + h/2 M_{k+1}

In Cayley coordinates ``F = cay(f) = I + 2 (hat f + hat f^2) / (1 + |f|^2)`` the
implicit equation reads, in vector form, ``2 (J f + f x J f) = (1 + |f|^2) a``
with ``a = h Pi_k + h^2/2 M_k`` (because ``hat(f) J_d + J_d hat(f) = hat(J f)``
and ``hat(f)^2 J_d - J_d hat(f)^2 = hat(f x J f)``): a polynomial, so Newton's
method needs no transcendental functions. It runs a fixed number of
iterations from ``f = J^-1 a / 2``, and the residual is checked: a step that
did not converge is reported as failed. The solve's derivative is the implicit
one at its root (one 3x3 solve, `_cayley_root`), so a derivative program carries
no iteration's tangent (``benchmarks/ablation.py``, ``LGVI grad``).
When ``M`` depends on ``Omega`` (feedback control), ``Pi_{k+1}`` is found by
fixed-point iteration (a contraction for ``h k_Omega / (2 J) < 1``).

Symplectic and momentum-preserving: the spatial angular momentum ``R J Omega``
is conserved to round-off for ``M = 0`` and the energy error stays bounded.

References: T. Lee, M. Leok, N. H. McClamroch, "A Lie group variational
integrator for the attitude dynamics of a rigid body with applications to the
3D pendulum", IEEE CCA 2005; "Lie group variational integrators for the full
body problem", Comput. Methods Appl. Mech. Engrg. 196 (2007) 2907–2924.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp

from .._scene import MechanicalScene
from .._so3 import _cross, _det, _dot, _hat, _mm, _mtv, _mv
from .._state import LieState
from .._updates import _exp_increment
from ._base import AbstractLieSolver


def _solve3(A, b):
    """``A^-1 b`` for a 3x3 ``A`` through the cofactor matrix (fuses under vmap)."""
    c0, c1, c2 = A[..., 0, :], A[..., 1, :], A[..., 2, :]
    cof = jnp.stack([_cross(c1, c2), _cross(c2, c0), _cross(c0, c1)], -2)
    return _mtv(cof, b) / _det(A)[..., None]


def _residual(f, J, a):
    """``G(f) = 2 (J f + f x J f) - (1 + |f|^2) a``: zero when ``F = cay(f)`` solves the step."""
    Jf = _mv(J, f)
    return 2.0 * (Jf + _cross(f, Jf)) - (1.0 + _dot(f, f))[..., None] * a


def _residual_jac(f, J, a):
    """``dG/df = 2 (J + hat(f) J - hat(J f)) - 2 a f^T``."""
    Jf = _mv(J, f)
    return 2.0 * (J + _mm(_hat(f), J) - _hat(Jf)) - 2.0 * a[..., :, None] * f[..., None, :]


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _cayley_root(iters, J, a, f):
    """``iters`` Newton iterations on ``G(f) = 0`` (`_residual`) from ``f``.

    Its derivative is the implicit one at the root it returns, ``df = -G_f^-1 dG``
    (``dG``: ``G``'s differential in ``J`` and ``a`` at fixed ``f``; the start's tangent
    does not enter): one 3x3 solve, not the derivative of every iteration. Where the step
    converged (its ``failed`` flag is false) that is the derivative of the step's exact
    solution, to the residual's round-off.
    """
    for _ in range(iters):
        f = f - _solve3(_residual_jac(f, J, a), _residual(f, J, a))
    return f


@_cayley_root.defjvp
def _cayley_root_jvp(iters, primals, tangents):
    J, a, f0 = primals
    f = _cayley_root(iters, J, a, f0)
    dJ, da, _ = tangents
    _, dG = jax.jvp(lambda J, a: _residual(f, J, a), (J, a), (dJ, da))
    return f, -_solve3(_residual_jac(f, J, a), dG)


def _cayley_m1(f):
    """``cay(f) - I``, where ``cay(f) = (I + hat f)(I - hat f)^-1``.

    ``cay(f) = I + 2 (hat f + hat f^2) / (1 + |f|^2)``.
    """
    t = _dot(f, f)
    c = (2.0 / (1.0 + t))[..., None, None]
    hat2 = f[..., :, None] * f[..., None, :] - t[..., None, None] * jnp.eye(3, dtype=f.dtype)
    return c * (_hat(f) + hat2)


class LGVI(AbstractLieSolver):
    """Lee–Leok–McClamroch Lie group variational integrator (order 2, symplectic).

    Works on scenes with one rigid body (`MechanicalScene` with state
    ``x = Omega``); kinematic rotations (e.g. a reference ``Rd``) move by the
    exponential midpoint rule ``Rd exp(h Omega_d(t + h/2))``.

    **Arguments:**

    - `newton_iters`: Newton iterations for ``F_k`` (quadratic convergence from
      an ``O(h^2)`` initial guess: 4 reach round-off for moderate ``h |Omega|``;
      raise it for large steps, non-convergence is reported in the status).
    - `torque_iters`: fixed-point iterations for ``Pi_{k+1}`` when the torque
      depends on the state.
    """

    newton_iters: int = eqx.field(static=True, default=4)
    torque_iters: int = eqx.field(static=True, default=3)

    @property
    def order(self) -> int:
        return 2

    def step(self, scene, t, y, h):
        dR, x1, failed = self.increment(scene, t, y, h)
        return LieState(y.R + dR, x1), failed

    def increment(self, scene, t, y, h):
        if not isinstance(scene, MechanicalScene) or y.x.shape[-1] != 3:
            raise TypeError("LGVI needs a rigid-body scene whose vector state is Omega alone")
        body = scene.body
        J = body.inertia
        Pi = _mv(J, y.x)
        M0 = scene.torque(t, y)
        p = Pi if M0 is None else Pi + 0.5 * h * M0
        a = h * p
        f = _cayley_root(self.newton_iters, J, a, 0.5 * body.omega_from_momentum(a))
        res = _residual(f, J, a)
        eps = jnp.finfo(f.dtype).eps
        scale = jnp.sqrt(_dot(a, a)) * (1.0 + _dot(f, f)) + jnp.finfo(f.dtype).tiny
        failed = ~(jnp.sqrt(_dot(res, res)) <= 100 * eps * scale)
        Fm1 = _cayley_m1(f)  # F - I: the update R + R (F - I) rounds in proportion to |f|
        dR_body = _mm(y.R[0], Fm1)
        kin = scene.kinematic_rates(t + 0.5 * h, y)
        if kin is None:
            dR = dR_body[None]
        else:
            dR = jnp.concatenate([dR_body[None], _exp_increment(y.R[1:], h * kin)], 0)
        R1 = y.R + dR
        Pi_half = _mtv(Fm1 + jnp.eye(3, dtype=f.dtype), p)
        if M0 is None:
            Pi1 = Pi_half
        else:
            Pi1 = Pi_half + 0.5 * h * M0
            for _ in range(self.torque_iters):
                y1 = LieState(R1, body.omega_from_momentum(Pi1))
                Pi1 = Pi_half + 0.5 * h * scene.torque(t + h, y1)
        return dR, body.omega_from_momentum(Pi1), failed
