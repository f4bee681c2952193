"""Suslov's problem: a rigid body whose angular velocity is orthogonal to a body vector.

The constraint ``<Omega, a> = 0`` (``a`` fixed in the body) is linear in the
velocity and not integrable: a nonholonomic constraint. The Lagrange–d'Alembert
principle adds a constraint torque along ``a`` to Euler's equations,

    J Omega' = (J Omega) x Omega + lambda a,     R' = R hat(Omega),

with the multiplier ``lambda`` chosen so that ``<Omega', a> = 0``:

    lambda = -<a, J^-1 ((J Omega) x Omega)> / <a, J^-1 a>.

The constraint torque does no work (``<Omega, lambda a> = 0``), so the energy
``1/2 <Omega, J Omega>`` is conserved; the Casimir ``|J Omega|`` of the free body
is not, and the spatial momentum ``R J Omega`` is not either. Since
``<a, Omega'> = 0`` holds for every ``Omega`` (not only on the constraint plane),
any Runge–Kutta-type method keeps the linear invariant ``<Omega, a>`` to
round-off.

For ``a`` not an eigenvector of ``J`` the reduced motion on each energy ellipse
of the plane ``a^perp`` runs from one steady rotation ``-Omega*`` to the
opposite one ``+Omega*``, where ``Omega*`` spans ``a^perp ∩ (J a)^perp``: the
flow contracts phase volume, which no Hamiltonian flow does.

References: G. K. Suslov, *Theoretical Mechanics*, 1946; A. M. Bloch,
*Nonholonomic Mechanics and Control*, 2nd ed., Springer 2015, sec. 1.7 and 5.8;
Yu. N. Fedorov, V. V. Kozlov, "Various aspects of n-dimensional rigid body
dynamics", AMS Transl. 168 (1995) 141–171.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ._dynamics import RigidBody
from ._scene import MechanicalScene, check_rotation, check_vector
from ._scenes import _as_body
from ._so3 import _cross, _dot, _is_concrete, _mv, _prep
from ._state import LieState
from ._types import Array, ArrayLike, Scalar, Vec3

#: Relative tolerance of the check ``|<Omega0, a>| <= tol |Omega0|`` in `suslov`, by
#: floating-point width: float64, and float32 (or narrower).
SUSLOV_CONSTRAINT_RTOL = {64: 1e-8, 32: 1e-5}


class Suslov(MechanicalScene):
    """Suslov's nonholonomic rigid body: state ``(R, Omega)`` with ``<Omega, a> = 0``.

    ``J Omega' = (J Omega) x Omega + lambda a``, ``R' = R hat(Omega)``, where the
    constraint torque ``lambda a`` keeps ``<Omega', a> = 0`` (see `multiplier`).
    Build it with `suslov`.

    **Fields:**

    - `body`: the `RigidBody` (energy: ``body.kinetic_energy(Omega)``).
    - `a`: the unit constraint vector in the body frame, shape `(3,)`.
    - `y0`: the initial `LieState`.

    References: A. M. Bloch, *Nonholonomic Mechanics and Control*, sec. 1.7.
    """

    body: RigidBody
    a: Vec3
    y0: LieState

    def multiplier(self, Omega: Vec3) -> Scalar:
        """``lambda = -<a, J^-1 ((J Omega) x Omega)> / <a, J^-1 a>``, shape `(...)`."""
        b = _mv(self.body.inertia_inv, self.a)  # J^-1 a (J symmetric)
        c = _cross(_mv(self.body.inertia, Omega), Omega)
        return -_dot(b, c) / _dot(self.a, b)

    def torque(self, t: Array, y: LieState) -> Vec3:
        """The constraint torque ``lambda a``, shape `(..., 3)`."""
        return self.multiplier(y.x[..., :3])[..., None] * self.a

    def constraint(self, Omega: Vec3) -> Scalar:
        """The constraint residual ``<Omega, a>`` (zero on the constraint), shape `(...)`."""
        return _dot(Omega, self.a)


def suslov_project(a: ArrayLike, Omega: ArrayLike) -> Vec3:
    """The nearest angular velocity that satisfies Suslov's constraint.

    ``Omega - <Omega, a> a / |a|^2``: the orthogonal projection onto the plane
    ``<Omega, a> = 0``.

    **Arguments:**

    - `a`: the constraint vector (any nonzero length), shape `(3,)`.
    - `Omega`: angular velocities, shape `(..., 3)`.

    **Returns:** shape `(..., 3)`, in the dtype of the promoted inputs.
    """
    a = _prep(a, "a", (3,))
    Omega = _prep(Omega, "Omega", (3,))
    dtype = jnp.result_type(a, Omega)
    a, Omega = a.astype(dtype), Omega.astype(dtype)
    a_hat = a / jnp.sqrt(_dot(a, a))
    return Omega - _dot(Omega, a_hat)[..., None] * a_hat


def _check_axis(a, dtype) -> Array:
    a = _prep(a, "a", (3,))
    if a.shape != (3,):
        raise ValueError(f"a must have shape (3,), got {tuple(a.shape)}")
    if _is_concrete(a):
        n = float(np.linalg.norm(np.asarray(a, dtype=np.float64)))
        if not n > 0:
            raise ValueError("a must be a nonzero vector (the constraint is <Omega, a> = 0), got 0")
        a_hat = np.asarray(a, dtype=np.float64) / n
        return jnp.asarray(a_hat, dtype)
    a = a.astype(dtype)
    return a / jnp.sqrt(_dot(a, a))


def suslov(
    inertia: ArrayLike | RigidBody, a: ArrayLike, R0: ArrayLike, Omega0: ArrayLike
) -> Suslov:
    """Suslov's problem: a rigid body with the nonholonomic constraint ``<Omega, a> = 0``.

    ``J Omega' = (J Omega) x Omega + lambda a``, ``R' = R hat(Omega)``, with
    ``lambda = -<a, J^-1 ((J Omega) x Omega)> / <a, J^-1 a>`` so that
    ``<Omega', a> = 0`` (Lagrange–d'Alembert). Energy is conserved, ``|J Omega|``
    is not. Every Runge–Kutta-type method (`RKMK4`, `CG3`, `CF4`, `LieEuler`,
    `RKMK45`, adaptive `RKMKTsit5`) keeps ``<Omega, a>`` to round-off. `LGVI`
    runs too (the constraint torque depends on ``Omega`` and is found by its
    fixed-point iteration), but it is not a nonholonomic integrator: it treats
    ``lambda a`` as an external torque, so ``<Omega, a>`` drifts by
    ``O(dt^2)`` instead of staying at round-off.

    **Arguments:**

    - `inertia`: a symmetric positive-definite `(3, 3)` inertia, 3 principal
      moments, or a `RigidBody`.
    - `a`: the constraint vector in the body frame, shape `(3,)`, nonzero and
      finite; it is normalised.
    - `R0`: initial attitude, shape `(3, 3)`, a rotation.
    - `Omega0`: initial body angular velocity, shape `(3,)`, on the constraint
      plane: ``|<Omega0, a>| <= tol |Omega0|`` with ``|a| = 1`` and ``tol = 1e-8``
      in float64, ``1e-5`` in float32 (`SUSLOV_CONSTRAINT_RTOL`); it is then projected
      onto the plane (a change of at most ``tol |Omega0|``) so that the run starts
      on the constraint to round-off. `suslov_project` makes any vector admissible.

    The dtype of the scene is that of ``R0``. Wrong shapes, NaN or inf, a zero
    ``a``, an inertia that is not symmetric positive definite, or an ``Omega0``
    off the plane raise a ``ValueError`` naming the argument (value checks run
    when the arguments are concrete, not under `jit`).

    **Returns:** a `Suslov` scene for `simulate`.

    References: A. M. Bloch, *Nonholonomic Mechanics and Control*, 2nd ed.,
    Springer 2015, sec. 1.7; Yu. N. Fedorov, V. V. Kozlov, AMS Transl. 168
    (1995) 141–171.
    """
    R0 = check_rotation(R0, "R0")
    dtype = R0.dtype
    body = _as_body(inertia, dtype)
    a_hat = _check_axis(a, dtype)
    Omega0 = check_vector(Omega0, "Omega0").astype(dtype)
    if _is_concrete(Omega0) and _is_concrete(a_hat):
        W = np.asarray(Omega0, dtype=np.float64)
        res = abs(float(W @ np.asarray(a_hat, dtype=np.float64)))
        rtol = SUSLOV_CONSTRAINT_RTOL[64 if jnp.finfo(dtype).bits >= 64 else 32]
        bound = rtol * float(np.linalg.norm(W)) + np.finfo(np.float64).tiny
        if res > bound:
            raise ValueError(
                f"Omega0 must satisfy the constraint <Omega0, a> = 0 (|a| = 1): "
                f"|<Omega0, a>| = {res:.3g} > {rtol:g} |Omega0| = {bound:.3g}; "
                "use so3jax.scenes.suslov_project(a, Omega0)"
            )
    Omega0 = Omega0 - _dot(Omega0, a_hat) * a_hat
    return Suslov(body=body, a=a_hat, y0=LieState(R0[None], Omega0))
