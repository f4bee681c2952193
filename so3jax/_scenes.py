"""Ready-made scenes. Each models no more than its experiment needs."""

from __future__ import annotations

from ._dynamics import RigidBody
from ._scene import MechanicalScene, check_rotation, check_vector
from ._state import LieState
from ._types import ArrayLike


def _cast_body(body: RigidBody, dtype) -> RigidBody:
    if body.inertia.dtype == dtype:
        return body
    return RigidBody(body.inertia.astype(dtype))


def _as_body(inertia, dtype) -> RigidBody:
    body = inertia if isinstance(inertia, RigidBody) else RigidBody(inertia)
    return _cast_body(body, dtype)


class FreeBody(MechanicalScene):
    """A torque-free rigid body: state ``(R, Omega)``, nothing else."""

    body: RigidBody
    y0: LieState


def free_body(inertia: ArrayLike | RigidBody, R0: ArrayLike, Omega0: ArrayLike) -> FreeBody:
    """The torque-free rigid body (Euler's equations with ``M = 0``).

    **Arguments:**

    - `inertia`: `(3, 3)` inertia, 3 principal moments, or a `RigidBody`.
    - `R0`: initial attitude, shape `(3, 3)`, a rotation (see `project`).
    - `Omega0`: initial body angular velocity, shape `(3,)`.

    The dtype of the scene is that of ``R0`` (pass float32 arrays for a
    float32 simulation).

    **Returns:** a `FreeBody` scene for `simulate`.
    """
    R0 = check_rotation(R0, "R0")
    Omega0 = check_vector(Omega0, "Omega0").astype(R0.dtype)
    body = _as_body(inertia, R0.dtype)
    return FreeBody(body=body, y0=LieState(R0[None], Omega0))
