"""What a scene is: an initial state on SO(3)^k x R^n and a vector field.

A scene bundles what one experiment needs and nothing more. Integrators only
see the protocol below; `MechanicalScene` specialises it to one rigid body
``(R, Omega)`` driven by a torque, plus optional *kinematic* rotations (such as a
reference attitude ``Rd`` with ``Rd' = Rd hat(Omega_d(t))``) that ride along.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._dynamics import RigidBody
from ._repr import module_repr
from ._so3 import _FULL, _is_concrete, _prep
from ._state import LieState, LieTangent
from ._types import Array


class Scene(eqx.Module):
    """Abstract scene: an initial state and a vector field on ``SO(3)^k x R^n``.

    A scene whose rotation groups ``y.R[g]`` move with time alone (not with
    the rest of the state: a reference attitude ``Rd' = Rd hat(Omega_d(t))``)
    lists them in the class attribute `time_driven_groups`. After a failure
    they run on instead of freezing with the rest of the state (they cannot
    have caused it), so a batch whose runs share their start computes them
    once for all runs.
    """

    y0: eqx.AbstractVar[LieState]
    time_driven_groups: ClassVar[tuple[int, ...]] = ()

    # Small concrete leaves (gains, inertia, reference parameters) print by value.
    __repr__ = module_repr

    @abc.abstractmethod
    def vector_field(self, t: Array, y: LieState) -> LieTangent:
        """Body velocities of the rotations and derivatives of the vector part."""

    @abc.abstractmethod
    def observe(self, t: Array, y: LieState) -> dict[str, Array]:
        """Named quantities saved in the `Trajectory` (at least ``R``, ``Omega``)."""

    def jump(self, t: Array, y: LieState) -> LieState:
        """Discrete map applied after every step (hybrid systems); identity by default.

        A hybrid controller keeps its logic variable in ``y.x`` (with zero
        derivative) and flips it here, e.g. the hysteresis of a quaternion
        controller.
        """
        return y

    def restarted(self, R0: Array) -> Scene:
        """The scene with what depends on the body's initial attitude recomputed for ``R0``.

        ``y0.R`` itself is left alone (`simulate` places ``R0``). Identity by
        default; a tracking scene re-initialises its controller's memory.
        """
        return self

    def with_inertia(self, body: RigidBody) -> Scene:
        """The scene rebuilt by its constructor around another body (same controller,
        reference and initial state; what depends on the inertia is recomputed).

        A `ValueError` for a scene that has no body inertia to replace.
        """
        raise ValueError(f"a {type(self).__name__} scene takes no other inertia")

    def fault(self, t: Array, y: LieState) -> Array | None:
        """Why a step from ``(t, y)`` fails, as a `Status` code (0: no cause known here).

        `simulate` asks once per run, after the loop, at the last good state of a
        run that stopped being finite, to name a cause the scene can tell (the
        quadrotor: a commanded attitude that is undefined). ``None`` (the default):
        the scene knows no causes, and the run's code stays "not finite".
        """
        return None

    def for_step(self, dt: Array, t0: Array) -> Scene:
        """The scene to integrate with fixed steps of ``dt`` from ``t0`` (itself by default).

        `simulate` calls it before stepping. A scene that depends on the step
        validates ``dt`` here (``ValueError`` naming it) and returns a copy that
        knows it: a sampled-data controller counts steps per control period, and
        takes its first sample from the initial state at ``t0``.
        """
        return self


class MechanicalScene(Scene):
    """One rigid body ``(R, Omega)`` under a torque, plus kinematic rotations.

    State layout: ``y.R[0]`` is the body attitude, ``y.R[1:]`` are kinematic
    rotations moving with body rates `kinematic_rates`, and ``y.x[:3]`` is the
    body angular velocity ``Omega``.

    ``R' = R hat(Omega)``, ``J Omega' = torque - Omega x J Omega``.
    """

    body: eqx.AbstractVar[RigidBody]

    def torque(self, t: Array, y: LieState) -> Array | None:
        """Body torque ``M(t, y)``, shape `(3,)`; ``None`` for a torque-free body."""
        return None

    def kinematic_rates(self, t: Array, y: LieState) -> Array | None:
        """Body rates of the kinematic rotations ``y.R[1:]``, shape `(k - 1, 3)`."""
        return None

    def angular_acceleration(self, t: Array, y: LieState) -> Array:
        """``Omega' = J^-1 (torque - Omega x J Omega)``, shape `(3,)`.

        A scene whose torque cancels part of Euler's equations in closed form (the
        geometric controller's feedforward: `Tracking`) overrides this with the
        closed-loop acceleration, the same to round-off in fewer operations.
        """
        return self.body.euler_rhs(y.x[..., :3], self.torque(t, y))

    def vector_field(self, t: Array, y: LieState) -> LieTangent:
        Omega = y.x[..., :3]
        dOmega = self.angular_acceleration(t, y)
        xi = Omega[..., None, :]
        kin = self.kinematic_rates(t, y)
        if kin is not None:
            xi = jnp.concatenate([xi, kin], axis=-2)
        dx = dOmega if y.x.shape[-1] == 3 else jnp.concatenate([dOmega, self.extra_rhs(t, y)], -1)
        return LieTangent(xi, dx)

    def extra_rhs(self, t: Array, y: LieState) -> Array:
        """Derivative of ``y.x[3:]`` for scenes that carry more than ``Omega``."""
        raise NotImplementedError

    def observe(self, t: Array, y: LieState) -> dict[str, Array]:
        return {"R": y.R[..., 0, :, :], "Omega": y.x[..., :3]}


def rotation_tolerance(dtype) -> float:
    """The largest ``||R^T R - I||_F`` an initial attitude of ``dtype`` may have."""
    return 1e-5 if jnp.finfo(dtype).bits < 64 else 1e-8


def not_rotation(R: Array) -> Array:
    """Traced: ``R`` (shape `(..., 3, 3)`) is not a rotation (`rotation_tolerance`)."""
    RtR = jnp.matmul(jnp.swapaxes(R, -1, -2), R, precision=_FULL)  # (TF32 errs above it)
    E = RtR - jnp.eye(3, dtype=R.dtype)
    err2 = jnp.sum(E * E, axis=(-2, -1))
    return ~(err2 <= rotation_tolerance(R.dtype) ** 2) | ~(jnp.linalg.det(R) > 0)


def check_rotation(R, name: str) -> Array:
    """Validate an initial attitude: shape (3, 3), finite, on SO(3) (eager only)."""
    R = _prep(R, name, (3, 3))
    if R.shape != (3, 3):
        raise ValueError(f"{name} must have shape (3, 3), got {tuple(R.shape)}")
    if _is_concrete(R):
        # NumPy, not jnp: under an active jit trace jnp ops on concrete arrays are staged.
        Rn = np.asarray(R, dtype=np.float64)
        err = float(np.linalg.norm(Rn.T @ Rn - np.eye(3)))
        det = float(np.linalg.det(Rn))
        if err > rotation_tolerance(R.dtype) or det <= 0:
            raise ValueError(
                f"{name} is not a rotation (||R^T R - I|| = {err:.3g}, det = {det:.3g}); "
                "use so3jax.project(R) to get the nearest rotation"
            )
    return R


def check_vector(v, name: str) -> Array:
    """Validate an initial vector: shape (3,), finite (eager only)."""
    v = _prep(v, name, (3,))
    if v.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {tuple(v.shape)}")
    return v
