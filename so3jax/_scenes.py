"""Ready-made scenes. Each models no more than its experiment needs."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._control import (
    AbstractController,
    ConstantRate,
    GeometricController,
    GeometricGains,
    QuaternionController,
    SinusoidalRate,
    _errors,
)
from ._dynamics import RigidBody
from ._scene import MechanicalScene, check_rotation, check_vector
from ._so3 import _exp_jit, _to_dtype, from_euler_zyx
from ._state import LieState
from ._types import ArrayLike


def _cast_body(body: RigidBody, dtype) -> RigidBody:
    if body.inertia.dtype == dtype:
        return body
    return RigidBody(_to_dtype(body.inertia, dtype))


def _as_body(inertia, dtype) -> RigidBody:
    body = inertia if isinstance(inertia, RigidBody) else RigidBody(inertia)
    return _cast_body(body, dtype)


class FreeBody(MechanicalScene):
    """A torque-free rigid body: state ``(R, Omega)``, nothing else."""

    body: RigidBody
    y0: LieState

    def with_inertia(self, body):
        return free_body(body, self.y0.R[0], self.y0.x)


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


# --------------------------------------------------------------------------
# Attitude tracking
# --------------------------------------------------------------------------

#: Duration of the seed scenario, in seconds.
SEED_DURATION = 10.0
#: Quadrotor inertia of Lee, Leok & McClamroch (CDC 2010), kg m^2.
SEED_INERTIA = (0.0820, 0.0845, 0.1377)
#: Their attitude gains ``(k_R, k_Omega)``.
SEED_GAINS = (8.81, 2.54)


class Tracking(MechanicalScene):
    """A rigid body tracking a reference attitude under a feedback controller.

    State: ``y.R = stack([R, Rd])`` (the body attitude and the reference
    attitude, which moves with ``Rd' = Rd hat(Omega_d(t))``) and
    ``y.x = [Omega, memory]`` where ``memory`` (``controller.memory_size``
    numbers, zero derivative) is updated after every step by `jump` (hybrid
    controllers). `observe` saves ``R``, ``Omega``, ``Rd``, ``M`` (the torque)
    and, in `Trajectory.extras`, ``e_R``, ``e_Omega`` and anything the
    controller observes.

    **Fields:**

    - `body`: the `RigidBody`.
    - `controller`: an `AbstractController`, e.g. `GeometricController`.
    - `reference`: any function ``t -> (Omega_d(t), dOmega_d(t))``.
    - `y0`: the initial `LieState`.
    """

    body: RigidBody
    controller: AbstractController
    reference: Callable
    y0: LieState
    time_driven_groups: ClassVar[tuple[int, ...]] = (1,)  # Rd

    def _reference(self, t, dtype):
        Omega_d, dOmega_d = self.reference(t)
        return jnp.asarray(Omega_d, dtype), jnp.asarray(dOmega_d, dtype)

    def _parts(self, t, y):
        R, Rd = y.R[..., 0, :, :], y.R[..., 1, :, :]
        Omega_d, dOmega_d = self._reference(t, y.R.dtype)
        return R, Rd, y.x[..., :3], y.x[..., 3:], Omega_d, dOmega_d

    def _memory(self, mem):
        return mem if self.controller.memory_size else None

    def torque(self, t, y):
        R, Rd, Omega, mem, Od, dOd = self._parts(t, y)
        return self.controller(t, self.body, R, Omega, Rd, Od, dOd, self._memory(mem))

    def angular_acceleration(self, t, y):
        # The controller's closed loop (`AbstractController.angular_acceleration`),
        # unless a subclass changed the torque (`so3jax._sweep_params.Disturbed`).
        if type(self).torque is not Tracking.torque:
            return super().angular_acceleration(t, y)
        R, Rd, Omega, mem, Od, dOd = self._parts(t, y)
        return self.controller.angular_acceleration(
            t, self.body, R, Omega, Rd, Od, dOd, self._memory(mem)
        )

    def kinematic_rates(self, t, y):
        Omega_d, _ = self._reference(t, y.R.dtype)
        return Omega_d[..., None, :]

    def extra_rhs(self, t, y):
        return jnp.zeros_like(y.x[..., 3:])

    def with_inertia(self, body):
        y0 = self.y0
        return tracking(body, self.controller, y0.R[0], y0.x[:3], y0.R[1], self.reference)

    def restarted(self, R0):
        if not self.controller.memory_size:
            return self
        memory = self.controller.init_memory(R0, self.y0.R[1]).astype(self.y0.x.dtype)
        return eqx.tree_at(lambda s: s.y0.x, self, self.y0.x.at[3:].set(memory))

    def jump(self, t, y):
        if not self.controller.memory_size:
            return y
        mem = self.controller.update_memory(y.R[..., 0, :, :], y.R[..., 1, :, :], y.x[..., 3:])
        return LieState(y.R, jnp.concatenate([y.x[..., :3], mem], -1))

    def observe(self, t, y):
        R, Rd, Omega, mem, Od, dOd = self._parts(t, y)
        M = self.controller(t, self.body, R, Omega, Rd, Od, dOd, self._memory(mem))
        e_R, e_Omega = _errors(R, Omega, Rd, Od)
        out = {"R": R, "Omega": Omega, "Rd": Rd, "M": M, "e_R": e_R, "e_Omega": e_Omega}
        if self.controller.memory_size:
            out.update(self.controller.observe(R, Rd, mem))
        return out


def _cast_floats(tree, dtype):
    """Every float array of ``tree`` as a (strongly typed) array of ``dtype``.

    Concrete arrays are cast in NumPy (`_to_dtype`): an eager JAX cast compiles on first use.
    """
    return jax.tree.map(lambda a: _to_dtype(a, dtype) if eqx.is_inexact_array(a) else a, tree)


def _check_reference(
    reference, dtype, names=("Omega_d", "dOmega_d"), example="so3jax.ConstantRate()"
):
    """A reference is a function of a scalar time returning two `(3,)` arrays ``names``."""
    a, b = names
    if not callable(reference):
        raise TypeError(
            f"reference must be a function t -> ({a}(t), {b}(t)), e.g. "
            f"{example}, got {type(reference).__name__}"
        )
    try:
        out = jax.eval_shape(reference, jax.ShapeDtypeStruct((), dtype))
    except Exception as e:
        raise ValueError(f"reference(t) failed on a scalar time: {e}") from e
    shapes = [getattr(o, "shape", None) for o in out] if isinstance(out, tuple | list) else None
    if shapes is None or len(shapes) != 2 or any(s != (3,) for s in shapes):
        raise ValueError(
            f"reference(t) must return ({a}, {b}), two arrays of shape (3,); "
            f"got {jax.tree.map(lambda o: o.shape, out)}"
        )


def tracking(
    inertia: ArrayLike | RigidBody,
    gains: GeometricGains | AbstractController,
    R0: ArrayLike,
    Omega0: ArrayLike,
    Rd0: ArrayLike,
    reference: Callable | None = None,
) -> Tracking:
    """Attitude tracking: a rigid body, a controller and a reference rate.

    ``R' = R hat(Omega)``, ``J Omega' = M - Omega x J Omega`` with
    ``M = controller(t, body, R, Omega, Rd, Omega_d(t), dOmega_d(t))``, and
    ``Rd' = Rd hat(Omega_d(t))``.

    **Arguments:**

    - `inertia`: `(3, 3)` inertia, 3 principal moments, or a `RigidBody`.
    - `gains`: a `GeometricGains` (the geometric controller) or any
      `AbstractController` (e.g. `QuaternionController`).
    - `R0`: initial attitude, shape `(3, 3)`, a rotation.
    - `Omega0`: initial body angular velocity, shape `(3,)`.
    - `Rd0`: initial reference attitude, shape `(3, 3)`, a rotation.
    - `reference`: a function ``t -> (Omega_d(t), dOmega_d(t))`` (shapes
      `(3,)`), e.g. `SinusoidalRate()`; default `ConstantRate()` (zero rate:
      regulation to ``Rd0``).

    The dtype of the scene is that of ``R0``; the controller's and the
    reference's parameters are cast to it.

    **Returns:** a `Tracking` scene for `simulate`.

    References: T. Lee, M. Leok, N. H. McClamroch, "Geometric tracking control
    of a quadrotor UAV on SE(3)", CDC 2010.
    """
    R0 = check_rotation(R0, "R0")
    dtype = R0.dtype
    Rd0 = check_rotation(Rd0, "Rd0").astype(dtype)
    Omega0 = check_vector(Omega0, "Omega0").astype(dtype)
    body = _as_body(inertia, dtype)
    if isinstance(gains, GeometricGains):
        controller = GeometricController(gains)
    elif isinstance(gains, AbstractController):
        controller = gains
    else:
        raise TypeError(
            "gains must be a GeometricGains or a controller (an AbstractController), "
            f"got {type(gains).__name__}"
        )
    controller = _cast_floats(controller, dtype)
    reference = ConstantRate() if reference is None else reference
    reference = _cast_floats(reference, dtype)
    _check_reference(reference, dtype)
    y0 = _tracking_state(controller, R0, Rd0, Omega0)
    return Tracking(body=body, controller=controller, reference=reference, y0=y0)


@eqx.filter_jit
def _tracking_state(controller, R0, Rd0, Omega0) -> LieState:
    """The initial state of a tracking scene (one compiled call when built eagerly)."""
    memory = controller.init_memory(R0, Rd0).astype(R0.dtype)
    return LieState(jnp.stack([R0, Rd0]), jnp.concatenate([Omega0, memory]))


def _float_dtype(dtype):
    return jnp.result_type(float) if dtype is None else jnp.dtype(dtype)


def seed(dtype=None) -> Tracking:
    """The seed scenario: geometric tracking of a sinusoidal reference by a quadrotor.

    ``J = diag(0.0820, 0.0845, 0.1377)`` kg m^2, ``k_R = 8.81``,
    ``k_Omega = 2.54`` (Lee, Leok & McClamroch, CDC 2010),
    ``R0 = from_euler_zyx(pi/3, -pi/4, pi/6)`` (``Psi(R0, I) = 0.954``),
    ``Omega0 = 0``, ``Rd0 = I``, reference `SinusoidalRate()` (0.5 rad/s,
    0.2 Hz, phases ``(0, 2 pi/3, 4 pi/3)``). Run it for `SEED_DURATION` = 10 s.

    **Arguments:**

    - `dtype`: float dtype of the scene (default: JAX's default float).

    **Returns:** a `Tracking` scene.
    """
    dtype = _float_dtype(dtype)
    pi = np.asarray(math.pi, dtype)  # NumPy: no eager JAX operations to compile
    R0 = from_euler_zyx(pi / 3, -pi / 4, pi / 6)
    return tracking(
        np.asarray(SEED_INERTIA, dtype),
        GeometricGains(*SEED_GAINS),
        R0,
        np.zeros(3, dtype),
        np.eye(3, dtype=dtype),
        SinusoidalRate(),
    )


def near_pi(angle: float = math.pi - 0.01, controller=None, dtype=None) -> Tracking:
    """Regulation from an almost 180-degree error: where the geometric controller is slow.

    ``R0 = exp(angle e3)``, ``Rd0 = I``, ``Omega0 = 0``, zero reference rate,
    the seed's body. With the geometric controller (default, the seed's
    gains) ``|e_R| = sin(angle)`` is tiny near ``pi``: the error function
    ``Psi`` leaves its maximum 2 slowly (exponentially, from a small push), then
    converges: stability is almost global, not global (``Psi = 2`` is an
    equilibrium set).

    **Arguments:**

    - `angle`: initial error angle in rad (default ``pi - 0.01``).
    - `controller`: a `GeometricGains` or controller (default: the seed gains).
    - `dtype`: float dtype.

    **Returns:** a `Tracking` scene.
    """
    dtype = _float_dtype(dtype)
    R0 = _exp_jit(np.asarray([0.0, 0.0, angle], dtype))
    controller = GeometricGains(*SEED_GAINS) if controller is None else controller
    return tracking(
        np.asarray(SEED_INERTIA, dtype),
        controller,
        R0,
        np.zeros(3, dtype),
        np.eye(3, dtype=dtype),
        ConstantRate(),
    )


#: Initial condition of `unwinding`: error angle about e3, in radians.
UNWINDING_ANGLE = 3.0
#: Initial condition of `unwinding`: spin rate about e3, in rad/s.
UNWINDING_RATE = 25.0


def unwinding(hysteresis: bool = False, delta: float = 0.2, dtype=None) -> Tracking:
    """Quaternion feedback through the antipode: unwinding versus hysteresis.

    The seed's body starts ``3.0`` rad from ``Rd0 = I`` about ``e3`` and spins
    towards ``pi`` at ``25`` rad/s (a flip manoeuvre); the error crosses 180
    degrees (``eta`` goes down to ``-0.32`` on the continuous lift of the error
    quaternion). The continuous controller
    (``hysteresis=False``, ``h = 1``) then pulls back through 180 degrees to
    ``q = +1``, rotating the long way (unwinding); the hybrid one
    (`QuaternionController` with hysteresis ``delta``) flips ``h`` once
    ``eta < -delta`` and settles at ``q = -1``, the same attitude, the short
    way. Gains ``k_q = 2 k_R``, ``k_Omega``: the seed's. Rotation travelled
    (RKMK4, 4 s): 4.57 rad unwinding against 3.28 = 2 pi - 3.0 with hysteresis.

    **Arguments:**

    - `hysteresis`: use the hybrid controller (``True``) or ``h = 1`` (``False``).
    - `delta`: hysteresis width.
    - `dtype`: float dtype.

    **Returns:** a `Tracking` scene with a `QuaternionController` (LGVI does not
    apply: the state carries the controller's memory).

    References: C. G. Mayhew, R. G. Sanfelice, A. R. Teel, IEEE TAC 56(11), 2011.
    """
    dtype = _float_dtype(dtype)
    k_R, k_Omega = SEED_GAINS
    ctrl = QuaternionController(2 * k_R, k_Omega, delta=delta, hysteresis=hysteresis)
    return tracking(
        np.asarray(SEED_INERTIA, dtype),
        ctrl,
        _exp_jit(np.asarray([0.0, 0.0, UNWINDING_ANGLE], dtype)),
        np.asarray([0.0, 0.0, UNWINDING_RATE], dtype),
        np.eye(3, dtype=dtype),
        ConstantRate(),
    )


def dzhanibekov(
    inertia: ArrayLike = (1.0, 2.0, 3.0),
    spin: float = 5.0,
    perturbation: float = 0.01,
    dtype=None,
) -> FreeBody:
    """The intermediate-axis (Dzhanibekov, tennis-racket) instability.

    A torque-free body spins at ``spin`` rad/s about its intermediate principal
    axis (``e2`` with the default moments ``(1, 2, 3)``), with a small
    transverse rate ``perturbation * spin`` about ``e1`` and ``e3``. Linearised,
    the perturbation grows like ``exp(lambda t)`` with
    ``lambda = spin sqrt((J2 - J1)(J3 - J2) / (J1 J3))``: the body flips
    (``Omega_2`` changes sign) periodically, about every
    ``~ 2 ln(1/perturbation) / lambda`` s (a few seconds by default), while
    energy and angular momentum stay constant.

    **Arguments:**

    - `inertia`: principal moments with the intermediate one second, shape `(3,)`.
    - `spin`: spin rate about ``e2``.
    - `perturbation`: relative transverse rate.
    - `dtype`: float dtype.

    **Returns:** a `FreeBody` scene.
    """
    dtype = _float_dtype(dtype)
    Jn = np.asarray(inertia, dtype=np.float64)
    if Jn.shape != (3,) or not Jn[0] < Jn[1] < Jn[2]:
        raise ValueError(
            f"inertia must be 3 principal moments J1 < J2 < J3 (e2 intermediate), got {Jn}"
        )
    J = np.asarray(inertia, dtype)
    Omega0 = np.asarray([perturbation * spin, spin, perturbation * spin], dtype)
    return free_body(J, np.eye(3, dtype=dtype), Omega0)
