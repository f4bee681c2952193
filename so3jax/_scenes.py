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
    _scalar_param,
)
from ._dynamics import RigidBody
from ._scene import MechanicalScene, check_rotation, check_vector
from ._sensors import SensorNoise, check_noise
from ._so3 import _as_float, _exp_jit, _is_concrete, _to_dtype, from_euler_zyx
from ._state import LieState
from ._types import Array, ArrayLike


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
    controllers). `observe` saves ``R``, ``Omega``, ``Rd``, ``M`` (the torque
    the actuators apply) and, in `Trajectory.extras`, ``e_R``, ``e_Omega`` and
    anything the controller observes.

    Optional actuator and environment model (each ``None`` by default; with all
    three ``None`` the scene integrates exactly the controller's closed loop):
    ``J Omega' = clip(M_cmd, -max_torque, max_torque) + disturbance - Omega x J Omega``,
    where ``M_cmd`` is the controller's torque, evaluated continuously or, with a
    `control_period`, sampled and held (a `SampledTracking` scene). With
    `max_torque` or `control_period`, ``extras["M_cmd"]`` holds the commanded torque
    (``M = clip(M_cmd)``); the disturbance is not part of the saved ``M``.

    **Fields:**

    - `body`: the `RigidBody`.
    - `controller`: an `AbstractController`, e.g. `GeometricController`.
    - `reference`: any function ``t -> (Omega_d(t), dOmega_d(t))``.
    - `y0`: the initial `LieState`.
    - `disturbance`: constant body disturbance torque in N m, shape `(3,)`, or ``None``.
    - `max_torque`: per-axis torque limit in N m (> 0), shape `()` or `(3,)`, or ``None``.
    - `control_period`: sampling period ``T`` in s (only in a `SampledTracking`), or
      ``None``.
    """

    body: RigidBody
    controller: AbstractController
    reference: Callable
    y0: LieState
    # `disturbance` first among the optional fields: `so3jax._sweep_params.Disturbed`
    # redeclares it without a default.
    disturbance: Array | None = None
    max_torque: Array | None = None
    control_period: Array | None = None
    time_driven_groups: ClassVar[tuple[int, ...]] = (1,)  # Rd

    def __check_init__(self):
        if self.control_period is not None and not isinstance(self, SampledTracking):
            raise ValueError(
                "a tracking scene with a control_period is a SampledTracking: build it with "
                "so3jax.scenes.tracking(..., control_period=T)"
            )
        shape = getattr(getattr(self.y0, "x", None), "shape", None)
        parts = "Omega, the controller's memory"
        width = 3 + getattr(self.controller, "memory_size", 0)
        if self.control_period is not None:
            parts, width = parts + ", the held torque and a step counter", width + 4
        if shape is not None and len(shape) >= 1 and shape[-1] != width:
            raise ValueError(
                f"y0.x must hold {width} numbers ({parts}), got {shape[-1]}; build the scene "
                "with so3jax.scenes.tracking"
            )

    @property
    def sampled(self) -> bool:
        """Whether the torque is sampled and held (a `control_period` is given)."""
        return self.control_period is not None

    def _reference(self, t, dtype):
        Omega_d, dOmega_d = self.reference(t)
        return jnp.asarray(Omega_d, dtype), jnp.asarray(dOmega_d, dtype)

    def _parts(self, t, y):
        R, Rd = y.R[..., 0, :, :], y.R[..., 1, :, :]
        Omega_d, dOmega_d = self._reference(t, y.R.dtype)
        Omega = y.x[..., :3]
        mem = y.x[..., 3 : 3 + self.controller.memory_size] if self.sampled else y.x[..., 3:]
        return R, Rd, Omega, mem, Omega_d, dOmega_d

    def _memory(self, mem):
        return mem if self.controller.memory_size else None

    def _commanded(self, t, y):
        """``M_cmd``: the torque held since the last sample, or the controller's now."""
        if self.sampled:
            return y.x[..., -4:-1]
        R, Rd, Omega, mem, Od, dOd = self._parts(t, y)
        return self.controller(t, self.body, R, Omega, Rd, Od, dOd, self._memory(mem))

    def _clip(self, M):
        """The torque the actuators apply for the command ``M``: ``clip(M, -max, max)``."""
        if self.max_torque is None:
            return M
        return jnp.clip(M, -self.max_torque, self.max_torque)

    def torque(self, t, y):
        """The body torque: the applied control torque plus the disturbance."""
        M = self._clip(self._commanded(t, y))
        return M if self.disturbance is None else M + self.disturbance

    def angular_acceleration(self, t, y):
        # The controller's closed loop (`AbstractController.angular_acceleration`),
        # unless the torque is not the controller's: a subclass changed it
        # (`so3jax._sweep_params.Disturbed`), or it is limited, held or disturbed.
        plain = self.disturbance is None and self.max_torque is None and not self.sampled
        if type(self).torque is not Tracking.torque or not plain:
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
        return tracking(
            body,
            self.controller,
            y0.R[0],
            y0.x[:3],
            y0.R[1],
            self.reference,
            max_torque=self.max_torque,
            control_period=self.control_period,
            disturbance=self.disturbance,
            noise=getattr(self, "noise", None),
        )

    def sweep_hook(self):
        """How `so3jax.sweep` runs this scene: `so3jax._sweep_hooks.AttitudeSweep`."""
        from ._sweep_hooks import AttitudeSweep

        return AttitudeSweep()

    def restarted(self, R0):
        if not self.controller.memory_size:
            return self
        memory = self.controller.init_memory(R0, self.y0.R[1]).astype(self.y0.x.dtype)
        x = self.y0.x
        x = x.at[3 : 3 + memory.shape[-1]].set(memory) if self.sampled else x.at[3:].set(memory)
        return eqx.tree_at(lambda s: s.y0.x, self, x)

    def jump(self, t, y):
        if not self.controller.memory_size:
            return y
        mem = self.controller.update_memory(y.R[..., 0, :, :], y.R[..., 1, :, :], y.x[..., 3:])
        return LieState(y.R, jnp.concatenate([y.x[..., :3], mem], -1))

    def observe(self, t, y):
        R, Rd, Omega, mem, Od, dOd = self._parts(t, y)
        if self.sampled:
            M = self._commanded(t, y)
        else:
            M = self.controller(t, self.body, R, Omega, Rd, Od, dOd, self._memory(mem))
        e_R, e_Omega = _errors(R, Omega, Rd, Od)
        out = {"R": R, "Omega": Omega, "Rd": Rd, "M": self._clip(M), "e_R": e_R, "e_Omega": e_Omega}
        if self.max_torque is not None or self.sampled:
            out["M_cmd"] = M
        if self.controller.memory_size:
            out.update(self.controller.observe(R, Rd, mem))
        return out


def _steps_per_hold(control_period, dt) -> int:
    """``control_period / dt``; ``ValueError`` unless ``dt`` divides the period.

    The rule of every sampled scene (`Quadrotor.steps_per_hold` too): the ratio must be
    a whole number ``>= 1`` to a relative ``1e-6``.
    """
    T = float(np.asarray(control_period, np.float64))
    ratio = T / float(np.asarray(dt, np.float64))
    n = round(ratio)
    if n < 1 or abs(ratio - n) > 1e-6 * max(1.0, ratio):
        raise ValueError(
            f"dt ({float(dt):g}) must divide control_period ({T:g}) into a whole "
            f"number of steps; got control_period / dt = {ratio:.6g}"
        )
    return n


def _sample_torque(scene, t, y):
    """The controller's torque at ``(t, y)`` (a sample of `SampledTracking`), from the
    state it reads (`SampledTracking.measured`)."""
    if getattr(scene, "noise", None) is not None:
        y = scene.measured(t, y)
    R, Rd, Omega, mem, Od, dOd = scene._parts(t, y)
    return scene.controller(t, scene.body, R, Omega, Rd, Od, dOd, scene._memory(mem))


#: `_sample_torque` compiled: `tracking` and `SampledTracking.for_step` sample outside any
#: ``jit`` (op by op, a first call would compile one small program per operation).
_sample_torque_jit = eqx.filter_jit(_sample_torque)


class SampledTracking(Tracking):
    """A `Tracking` scene whose controller is sampled and held (zero-order hold).

    The torque is computed at ``t0 + k T`` (``T = control_period``) from the state at
    that time and held until the next sample, as flight software runs a controller.
    ``y.x = [Omega, memory, M_held, c]``: the held command and the number of steps
    since the last sample, both with zero derivative; `jump` (after every step) first
    updates the controller's memory, then samples when ``c`` reaches ``T / dt``.
    `simulate` tells the scene its step through `for_step`, which checks that ``dt``
    divides ``T`` (the quadrotor's rule, `Quadrotor.steps_per_hold`) and takes the
    first sample from the initial state. Fixed steps only: adaptive steps raise a
    ``ValueError``.

    **Fields:** those of `Tracking`, and

    - `steps_per_sample`: ``T / dt``, set by `for_step` (``None`` before).

    ``noise`` is ``None`` here (a class attribute: the controller reads the true
    state); `tracking` given a `SensorNoise` builds a `NoisyTracking`, which carries
    it as a field, so that a scene without noise keeps its pytree and its program.
    """

    steps_per_sample: Array | None = None
    noise: ClassVar[SensorNoise | None] = None

    def measured(self, t, y) -> LieState:
        """The state the controller reads at a sample at ``t``: ``y`` itself without
        `noise`, else ``y`` with the body attitude and rate perturbed
        (`SensorNoise.perturb`, at the sample ``round(t / control_period)``)."""
        if self.noise is None:
            return y
        R, Omega = self.noise.perturb(t, self.control_period, y.R[..., 0, :, :], y.x[..., :3])
        Rs = jnp.concatenate([R[..., None, :, :], y.R[..., 1:, :, :]], -3)
        return LieState(Rs, jnp.concatenate([Omega, y.x[..., 3:]], -1))

    def steps_per_hold(self, dt) -> int:
        """``control_period / dt``; ``ValueError`` unless ``dt`` divides the period.

        Call it eagerly where ``dt`` and the period are known (a traced period
        inside ``jit`` cannot be checked; `for_step` then rounds the ratio).
        """
        return _steps_per_hold(self.control_period, dt)

    def for_step(self, dt, t0):
        """Record ``T / dt`` (``dt`` must divide ``T``) and sample the controller at ``t0``.

        A state whose step counter is 0 sits at a sample time: its held torque is
        recomputed from ``(t0, y0)``, so a scene whose gains were swapped
        (`eqx.tree_at`, `tune`) or that was restarted elsewhere starts from its own
        first sample. A restart inside a hold (counter > 0) keeps the held torque.
        """
        T = self.control_period
        if _is_concrete(dt) and _is_concrete(T):
            n = jnp.asarray(self.steps_per_hold(dt), T.dtype)
        else:
            n = jnp.maximum(jnp.round(T / dt), 1.0).astype(T.dtype)
        scene = eqx.tree_at(lambda s: s.steps_per_sample, self, n, is_leaf=lambda a: a is None)
        y = self.y0
        M = _sample_torque_jit(self, jnp.asarray(t0, y.x.dtype), y)
        at_sample = (y.x[..., -1] == 0)[..., None]
        held = jnp.where(at_sample, M, y.x[..., -4:-1])
        x = jnp.concatenate([y.x[..., :-4], held, y.x[..., -1:]], -1)
        return eqx.tree_at(lambda s: s.y0, scene, LieState(y.R, x))

    def restarted(self, R0):
        """The scene restarted from ``R0`` at a sample time (`for_step` then samples).

        ``R0`` is also written into ``y0.R[0]``: the first sample needs it, and a
        start given apart (`simulate_from`) then agrees with the scene's own.
        """
        scene = super().restarted(R0)
        y0 = scene.y0
        R = y0.R.at[0].set(jnp.asarray(R0, y0.R.dtype))
        x = y0.x.at[-1].set(0.0)
        return eqx.tree_at(lambda s: s.y0, scene, LieState(R, x))

    def jump(self, t, y):
        if self.steps_per_sample is None:
            raise ValueError(
                "a sampled-data tracking scene (control_period given) runs with fixed steps "
                "that divide control_period: simulate(scene, method, dt, n_steps); adaptive "
                "steps do not apply"
            )
        m = self.controller.memory_size
        R, Rd = y.R[..., 0, :, :], y.R[..., 1, :, :]
        if m:
            mem = self.controller.update_memory(R, Rd, y.x[..., 3 : 3 + m])
            y = LieState(y.R, jnp.concatenate([y.x[..., :3], mem, y.x[..., 3 + m :]], -1))
        count = y.x[..., -1] + 1.0
        sample = count > self.steps_per_sample - 0.5
        held = jnp.where(sample[..., None], _sample_torque(self, t, y), y.x[..., -4:-1])
        count = jnp.where(sample, jnp.zeros_like(count), count)
        x = jnp.concatenate([y.x[..., :-4], held, count[..., None]], -1)
        return LieState(y.R, x)


class NoisyTracking(SampledTracking):
    """A `SampledTracking` scene whose controller reads a noisy attitude and rate.

    **Fields:** those of `SampledTracking`, and

    - `noise`: a `SensorNoise` (its `attitude` and `rate` apply), drawn at each
      sample (`SampledTracking.measured`).
    """

    noise: SensorNoise | None = None

    def for_step(self, dt, t0):
        """`for_step` of the scene without noise's, with the noise's key as raw words
        (`SensorNoise.unwrapped`): the step draws by integer arithmetic alone."""
        scene = super().for_step(dt, t0)
        return eqx.tree_at(lambda s: s.noise, scene, scene.noise.unwrapped())


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
    max_torque: ArrayLike | None = None,
    control_period: ArrayLike | None = None,
    disturbance: ArrayLike | None = None,
    noise: SensorNoise | None = None,
) -> Tracking:
    """Attitude tracking: a rigid body, a controller and a reference rate.

    ``R' = R hat(Omega)``, ``J Omega' = M + d - Omega x J Omega`` with
    ``M = clip(M_cmd, -max_torque, max_torque)`` per body axis,
    ``M_cmd = controller(t, body, R, Omega, Rd, Omega_d(t), dOmega_d(t))``, and
    ``Rd' = Rd hat(Omega_d(t))``. With a `control_period` ``T``, ``M_cmd`` is
    evaluated at ``t0 + k T`` from the state at that time and held until the next
    sample (zero-order hold): `simulate` then needs fixed steps ``dt`` that divide
    ``T`` (``T / dt`` a whole number to a relative ``1e-6``, as for the quadrotor),
    and the initial state holds the sample at ``t = 0``.

    With `max_torque`, `control_period` and `disturbance` all ``None`` (the default)
    the scene is the controller's closed loop alone: the options add no leaf and no
    operation to its program. The saved ``M`` is the applied control torque (clipped,
    without ``d``); with `max_torque` or `control_period` the commanded one is in
    ``Trajectory.extras["M_cmd"]``.

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
    - `max_torque`: the actuators' limit in N m (> 0) on each body axis, a scalar or
      shape `(3,)`, or ``None`` (no limit). The clip is differentiable in the gains
      and in `max_torque` away from where a component meets the limit.
    - `control_period`: ``T`` in s (> 0), a scalar, for sampled-and-held control, or
      ``None`` (continuous control).
    - `disturbance`: a constant body torque ``d`` in N m, shape `(3,)`, added to the
      applied torque (the meaning and sign of `sweep`'s ``params["disturbance"]``),
      or ``None``.
    - `noise`: a `SensorNoise` (its `attitude` and `rate`; `position` and `velocity`
      must be 0): at each sample the controller reads ``R exp(hat(xi_R))`` and
      ``Omega + xi_Omega`` (`SampledTracking.measured`); the body and the saved state
      are not perturbed. Needs `control_period`. ``None``: the true state.

    The dtype of the scene is that of ``R0``; the controller's and the
    reference's parameters and the options are cast to it. Bad shapes raise a
    ``ValueError`` naming the argument; so do bad values when they are concrete
    (under `jit`/`vmap` they are not checked).

    **Returns:** a `Tracking` scene for `simulate` (a `SampledTracking` with a
    `control_period`).

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
    options = {
        "max_torque": _max_torque_arg(max_torque, dtype),
        "control_period": _control_period_arg(control_period, dtype),
        "disturbance": _disturbance_arg(disturbance, dtype),
    }
    noise = check_noise(noise, options["control_period"], dtype, attitude_only=True)
    y0 = _tracking_state(controller, R0, Rd0, Omega0)
    if options["control_period"] is None:
        return Tracking(body=body, controller=controller, reference=reference, y0=y0, **options)
    T = options.pop("control_period")
    continuous = Tracking(body=body, controller=controller, reference=reference, y0=y0, **options)
    y0 = _hold_initial_torque(continuous)
    if noise is not None:
        options["noise"] = noise
    return (SampledTracking if noise is None else NoisyTracking)(
        body=body, controller=controller, reference=reference, y0=y0, control_period=T, **options
    )


def _max_torque_arg(value, dtype):
    """`max_torque` checked (shape `()` or `(3,)`; concrete: positive and finite) and cast."""
    if value is None:
        return None
    a = _as_float(value)
    if a.shape not in ((), (3,)):
        raise ValueError(
            f"max_torque must be a scalar or a 3-vector (N m per body axis), got shape {a.shape}"
        )
    if _is_concrete(a):
        an = np.asarray(a, np.float64)
        if not (np.all(np.isfinite(an)) and np.all(an > 0)):
            raise ValueError(f"max_torque must be positive and finite, got {an}")
    return _to_dtype(a, dtype)


def _control_period_arg(value, dtype):
    """`control_period` checked (a scalar; concrete: positive and finite) and cast."""
    if value is None:
        return None
    return _to_dtype(_scalar_param(value, "control_period", positive=True), dtype)


def _disturbance_arg(value, dtype):
    """`disturbance` checked (shape `(3,)`; concrete: finite) and cast."""
    if value is None:
        return None
    a = _as_float(value)
    if a.shape != (3,):
        raise ValueError(
            f"disturbance must be a 3-vector (a body torque in N m), got shape {a.shape}"
        )
    if _is_concrete(a) and not np.all(np.isfinite(np.asarray(a))):
        raise ValueError(f"disturbance must be finite, got {np.asarray(a)}")
    return _to_dtype(a, dtype)


@eqx.filter_jit
def _hold_initial_torque(scene: Tracking) -> LieState:
    """The initial state of ``scene`` (continuous control) with the torque sampled at
    ``t = 0`` held and a step counter of 0 appended (one compiled call)."""
    y0 = scene.y0
    M = _sample_torque(scene, jnp.zeros((), y0.x.dtype), y0)
    return LieState(y0.R, jnp.concatenate([y0.x, M, jnp.zeros(1, y0.x.dtype)]))


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
