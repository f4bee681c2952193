"""The rigid body: inertia, Euler's equations and the conserved quantities."""

from __future__ import annotations

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._repr import module_repr
from ._so3 import _as_float, _cross, _dot, _is_concrete, _mv
from ._types import ArrayLike, Mat3, Rot, Scalar, Vec3


class RigidBody(eqx.Module):
    """A rigid body, described by its body-frame inertia tensor ``J``.

    Dynamics: ``R' = R hat(Omega)``, ``J Omega' + Omega x J Omega = M``.

    **Arguments:**

    - `inertia`: a symmetric positive-definite `(3, 3)` matrix, or the three
      principal moments `(3,)` (then ``J = diag(inertia)``). Anything else is a
      ``ValueError`` saying why. Principal moments that violate the triangle
      inequality (``J1 + J2 >= J3`` and permutations; no physical body has
      them) give a warning.

    Attributes: `inertia` (the `(3, 3)` matrix) and `inertia_inv`.
    """

    inertia: Mat3
    inertia_inv: Mat3

    __repr__ = module_repr

    def __init__(self, inertia: ArrayLike):
        J = _as_float(inertia)
        if J.shape not in ((3,), (3, 3)):
            raise ValueError(
                f"inertia must be a (3, 3) matrix or 3 principal moments, got shape {J.shape}"
            )
        if _is_concrete(J):
            Jn = np.asarray(J, dtype=np.float64)
            Jn = np.diag(Jn) if Jn.shape == (3,) else Jn
            if not np.all(np.isfinite(Jn)):
                raise ValueError("inertia contains NaN or inf")
            scale = max(np.abs(Jn).max(), np.finfo(np.float64).tiny)
            if np.abs(Jn - Jn.T).max() > 1e-6 * scale:
                raise ValueError(f"inertia must be symmetric, got\n{Jn}")
            ev = np.linalg.eigvalsh(0.5 * (Jn + Jn.T))
            if ev.min() <= 0:
                raise ValueError(
                    f"inertia must be positive definite; its eigenvalues are {ev.tolist()}"
                )
            a, b, c = ev
            if a + b < c * (1 - 1e-12):
                warnings.warn(
                    f"principal moments {ev.tolist()} violate the triangle inequality "
                    "J1 + J2 >= J3; no physical rigid body has them",
                    stacklevel=2,
                )
        self.inertia, self.inertia_inv = _inertia_matrices(J)

    def euler_rhs(self, Omega: Vec3, M: Vec3 | None = None) -> Vec3:
        """Angular acceleration ``Omega' = J^-1 (M - Omega x J Omega)``.

        **Arguments:**

        - `Omega`: body angular velocity, shape `(..., 3)`.
        - `M`: body torque, shape `(..., 3)`; zero if omitted.

        **Returns:** shape `(..., 3)`.
        """
        JO = _mv(self.inertia, Omega)
        rhs = -_cross(Omega, JO)
        if M is not None:
            rhs = rhs + M
        return _mv(self.inertia_inv, rhs)

    def kinetic_energy(self, Omega: Vec3) -> Scalar:
        """``T = 1/2 Omega . J Omega``, shape `(...)`."""
        return 0.5 * _dot(Omega, _mv(self.inertia, Omega))

    def body_momentum(self, Omega: Vec3) -> Vec3:
        """Body angular momentum ``Pi = J Omega``, shape `(..., 3)`."""
        return _mv(self.inertia, Omega)

    def spatial_momentum(self, R: Rot, Omega: Vec3) -> Vec3:
        """Spatial angular momentum ``pi = R J Omega`` (conserved when torque-free)."""
        return _mv(R, _mv(self.inertia, Omega))

    def casimir(self, Omega: Vec3) -> Scalar:
        """The Casimir ``|Pi|^2 / 2`` of the Lie-Poisson bracket, shape `(...)`."""
        Pi = self.body_momentum(Omega)
        return 0.5 * _dot(Pi, Pi)

    def omega_from_momentum(self, Pi: Vec3) -> Vec3:
        """``Omega = J^-1 Pi``."""
        return _mv(self.inertia_inv, Pi)


@jax.jit
def _inertia_matrices(J):
    """``(J, J^-1)`` for principal moments or a matrix (symmetrised): one compiled call.

    Eagerly, the same operations compiled one program each on first use, LAPACK's
    inverse among them; principal moments need none (``1 / J_i`` is what
    the LU inverse of a diagonal matrix gives, to the bit).
    """
    if J.shape == (3,):
        return jnp.diag(J), jnp.diag(1 / J)
    J = 0.5 * (J + J.T)
    return J, jnp.linalg.inv(J)
