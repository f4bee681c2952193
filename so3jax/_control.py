"""Attitude tracking control: errors, the geometric controller, references.

The geometric controller of Lee, Leok & McClamroch is a pure function of
``(gains, body, R, Omega, Rd, Omega_d, dOmega_d)``, so `jax.vmap` sweeps gains
and attitudes and `jax.grad` differentiates through it (gains are arrays, never
static). A *reference* is any function ``t -> (Omega_d(t), dOmega_d(t))``; the
reference attitude ``Rd`` is integrated alongside the state
(``Rd' = Rd hat(Omega_d)``), see `scenes.tracking`.

A *controller* is an `eqx.Module` called as
``controller(t, body, R, Omega, Rd, Omega_d, dOmega_d, memory) -> M``. Hybrid
controllers keep a small memory (``memory_size`` numbers riding in the state,
constant between steps) updated by ``update_memory`` after every step: the
quaternion controller of Mayhew, Sanfelice & Teel keeps its logic variable
``h = +-1`` and a continuous lift of the error quaternion there.
"""

from __future__ import annotations

import abc
import functools
import math
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from ._dynamics import RigidBody
from ._engine.passes.frames import Frame, dense, frame_rule, right_or_zero
from ._repr import module_repr
from ._so3 import _as_float, _cross, _dot, _is_concrete, _mm, _mT, _mv, _prep, _to_quat, _vee
from ._types import Array, ArrayLike, Rot, Scalar, Vec3

# --------------------------------------------------------------------------
# Errors and the geometric torque
# --------------------------------------------------------------------------


def _check_gain(value, name: str) -> Array:
    k = _as_float(value)
    if k.shape not in ((), (3,)):
        raise ValueError(
            f"{name} must be a scalar or a 3-vector (one gain per body axis), got shape "
            f"{k.shape}"
            + (
                f"; to batch gains, vmap the constructor: jax.vmap({name.split('.')[0]})(...)"
                if "." in name
                else "; to run a batch of gains, vmap over them"
            )
        )
    if _is_concrete(k):
        kn = np.asarray(k, dtype=np.float64)
        if not np.all(np.isfinite(kn)):
            raise ValueError(f"{name} must be finite, got {kn}")
        if np.any(kn < 0):
            raise ValueError(f"{name} must be non-negative, got {kn}")
    return k


class GeometricGains(eqx.Module):
    """Gains of the geometric attitude controller.

    ``M = -k_R e_R - k_Omega e_Omega + ...`` (see `geometric_torque`). Each gain
    is a scalar or a 3-vector (a diagonal gain, one value per body axis). The
    fields are arrays, so `jax.grad` with respect to a `GeometricGains` works
    and ``jax.vmap(GeometricGains)(k_R_batch, k_Omega_batch)`` builds a batch.

    **Arguments:**

    - `k_R`: attitude gain (>= 0, finite), shape `()` or `(3,)`.
    - `k_Omega`: angular-velocity gain (>= 0, finite), shape `()` or `(3,)`.

    Negative or non-finite gains raise ``ValueError`` when the values are
    concrete (under `jit`/`vmap` they are not checked).
    """

    k_R: Array
    k_Omega: Array

    __repr__ = module_repr

    def __init__(self, k_R: ArrayLike, k_Omega: ArrayLike):
        self.k_R = _check_gain(k_R, "GeometricGains.k_R")
        self.k_Omega = _check_gain(k_Omega, "GeometricGains.k_Omega")


def _errors(R, Omega, Rd, Omega_d):
    """``(e_R, e_Omega)`` without input checks."""
    e_R, (a,) = _errors_and_rates(R, Rd, (Omega_d,))
    return e_R, Omega - a


@jax.custom_jvp
def _errors_and_rates(R, Rd, vs):
    """``e_R = 1/2 vee(Rd^T R - R^T Rd)`` and ``R^T Rd v`` for each ``v`` in ``vs``.

    ``R^T Rd`` once, and each product with a vector once: ``e_Omega`` and the
    feedforward term both need ``R^T Rd Omega_d``, and the scalarized programs do not
    merge two copies of it (15 operations per evaluation, per run and per tangent
    column). Forming ``R^T (Rd v)`` and six entries of ``Rd^T R`` instead (fewer
    operations on the run's state when a batch shares ``Rd``) gains nothing in a batch
    and makes a single run slower (more, smaller kernels).
    """
    RtRd = _mm(_mT(R), Rd)
    return _vee(_mT(RtRd)), tuple(_mv(RtRd, v) for v in vs)


@functools.partial(_errors_and_rates.defjvp, symbolic_zeros=True)
def _errors_and_rates_jvp(primals, tangents):
    """Autodiff's tangent, written out (so that `_errors_and_rates_frame` has a function
    to attach to): ``dE = dR^T Rd + R^T dRd``, ``de_R = vee(dE^T)``, ``d(E v) = dE v + E dv``."""
    R, Rd, vs = primals
    dR, dRd, dvs = tangents
    RtRd = _mm(_mT(R), Rd)
    parts = []
    if not isinstance(dR, SymbolicZero):
        parts.append(_mm(_mT(dR), Rd))
    if not isinstance(dRd, SymbolicZero):
        parts.append(_mm(_mT(R), dRd))
    dE = functools.reduce(jnp.add, parts) if parts else None
    return _errors_tangent(RtRd, vs, dE, dvs, [None] * len(vs))


def _errors_tangent(RtRd, vs, dE, dvs, rotated, a=None):
    """Values and tangents of `_errors_and_rates` from ``E = R^T Rd`` (and ``a``, the
    products ``E v`` if formed) and ``dE`` (``None``: zero) plus, per ``v``, ``rotated`` (a
    tangent of ``E v`` found apart, or ``None``)."""
    a = tuple(_mv(RtRd, v) for v in vs) if a is None else tuple(a)
    out = (_vee(_mT(RtRd)), a)
    de = jnp.zeros_like(out[0]) if dE is None else _vee(_mT(dE))
    das = []
    for v, dv, a, r in zip(vs, dvs, out[1], rotated, strict=True):
        terms = [] if dE is None else [_mv(dE, v)]
        if r is not None:
            terms.append(r)
        if dv is not None and not isinstance(dv, SymbolicZero):
            terms.append(_mv(RtRd, dv))
        da = functools.reduce(jnp.add, terms) if terms else jnp.zeros_like(a)
        das.append(jnp.broadcast_to(da, a.shape).astype(a.dtype))
    return out, (jnp.broadcast_to(de, out[0].shape).astype(out[0].dtype), tuple(das))


@frame_rule(_errors_and_rates)
def _errors_and_rates_frame(xs, ts):
    """`_errors_and_rates` with ``dR = R hat(xi)``, ``dRd = Rd hat(zeta)``
    (`so3jax._engine.passes.frames`):
    ``dE = -hat(xi) E + E hat(zeta)``, so ``d(E v) = E v x ... = -xi x (E v) + E (zeta x v)
    + E dv`` (9 operations for ``-xi x E v`` where ``dR^T Rd v`` took 45 + 15); ``e_R``'s
    six entries of ``dE`` from the frames."""
    R, Rd, *vs = xs
    tR, tRd, *tvs = ts
    if any(isinstance(t, Frame) for t in tvs) or not (right_or_zero(tR) and right_or_zero(tRd)):
        return None
    RtRd = _mm(_mT(R), Rd)
    a = [_mv(RtRd, v) for v in vs]
    dE, rotated = None, [None] * len(vs)
    if tR is not None:  # d(R^T) Rd = -hat(xi) R^T Rd
        dE = dense(RtRd, Frame(-tR.xi, left=True))
        rotated = [_cross(ai, tR.xi) for ai in a]  # -xi x (E v)
    if tRd is not None:
        dEd = dense(RtRd, tRd)
        dE = dEd if dE is None else dE + dEd
        rotated = [
            _mv(RtRd, _cross(tRd.xi, v)) if r is None else r + _mv(RtRd, _cross(tRd.xi, v))
            for r, v in zip(rotated, vs, strict=True)
        ]
    out, (de, das) = _errors_tangent(RtRd, vs, None, tvs, rotated, a)
    if dE is not None:
        de = _vee(_mT(dE)).astype(de.dtype)
    return [out[0], *out[1]], [de, *das]


def _reference_term(body: RigidBody, Omega, a, b):
    """``J (hat(Omega) a - b)`` with ``a = R^T Rd Omega_d`` and ``b = R^T Rd dOmega_d``:
    the part of `_feedforward` that the closed loop keeps (`_closed_loop`)."""
    return _mv(body.inertia, _cross(Omega, a) - b)


def _feedforward(body: RigidBody, Omega, a, b):
    """``Omega x J Omega - J (hat(Omega) a - b)`` (`_reference_term`)."""
    return _cross(Omega, _mv(body.inertia, Omega)) - _reference_term(body, Omega, a, b)


def _geometric_feedback(gains, R, Omega, Rd, Omega_d, dOmega_d):
    """``(-k_R e_R - k_Omega e_Omega, a, b)``: the torque less `_feedforward`."""
    e_R, (a, b) = _errors_and_rates(R, Rd, (Omega_d, dOmega_d))
    return -gains.k_R * e_R - gains.k_Omega * (Omega - a), a, b


def _geometric_torque(gains, body, R, Omega, Rd, Omega_d, dOmega_d):
    feedback, a, b = _geometric_feedback(gains, R, Omega, Rd, Omega_d, dOmega_d)
    return feedback + _feedforward(body, Omega, a, b)


def _closed_loop(body: RigidBody, feedback, Omega, a, b):
    """``Omega'`` under the torque ``feedback + _feedforward(body, Omega, a, b)``, with the
    gyroscopic terms cancelled.

    ``J Omega' = M - Omega x J Omega`` and the feedforward is ``Omega x J Omega - J
    (hat(Omega) a - b)``, so ``Omega' = J^-1 (feedback - J (hat(Omega) a - b))`` (for the
    geometric controller, the error dynamics ``J e_Omega' = -k_R e_R - k_Omega e_Omega``
    of Lee, Leok & McClamroch, CDC 2010). The same function of ``body.inertia`` and
    ``body.inertia_inv`` as `RigidBody.euler_rhs` of the torque, to round-off,
    derivatives included (also when a caller replaced one of the two leaves: ``J^-1 J``
    is not simplified), without forming ``Omega x J Omega`` twice: 2 fewer products of a
    matrix with a vector and 2 fewer cross products per evaluation, per run and per
    tangent column.
    """
    return _mv(body.inertia_inv, feedback - _reference_term(body, Omega, a, b))


def tracking_errors(R: Rot, Omega: Vec3, Rd: Rot, Omega_d: Vec3) -> tuple[Vec3, Vec3]:
    """Attitude and angular-velocity tracking errors on SO(3).

    ``e_R = 1/2 vee(Rd^T R - R^T Rd)``, ``e_Omega = Omega - R^T Rd Omega_d``
    (both in the body frame; ``e_R = sin(angle) axis`` of ``Rd^T R``).

    **Arguments:**

    - `R`: attitude, shape `(..., 3, 3)`.
    - `Omega`: body angular velocity, shape `(..., 3)`.
    - `Rd`: desired attitude, shape `(..., 3, 3)`.
    - `Omega_d`: desired angular velocity (in the desired frame), shape `(..., 3)`.

    **Returns:** ``(e_R, e_Omega)``, each of shape `(..., 3)` (leading axes broadcast).

    References: T. Lee, M. Leok, N. H. McClamroch, "Geometric tracking control
    of a quadrotor UAV on SE(3)", CDC 2010, eqs. (10)–(11).
    """
    R = _prep(R, "R", (3, 3))
    Omega = _prep(Omega, "Omega", (3,))
    Rd = _prep(Rd, "Rd", (3, 3))
    Omega_d = _prep(Omega_d, "Omega_d", (3,))
    e_R, e_Omega = _errors(R, Omega, Rd, Omega_d)
    return e_R, e_Omega


def _check_gains_body(gains, body):
    if not isinstance(gains, GeometricGains):
        raise TypeError(f"gains must be a GeometricGains, got {type(gains).__name__}")
    if not isinstance(body, RigidBody):
        raise TypeError(f"body must be a RigidBody, got {type(body).__name__}")


def geometric_torque(
    gains: GeometricGains,
    body: RigidBody,
    R: Rot,
    Omega: Vec3,
    Rd: Rot,
    Omega_d: Vec3,
    dOmega_d: Vec3,
) -> Vec3:
    """The geometric attitude tracking controller of Lee, Leok & McClamroch.

    ``M = -k_R e_R - k_Omega e_Omega + Omega x J Omega
    - J (hat(Omega) R^T Rd Omega_d - R^T Rd dOmega_d)``, with ``e_R``,
    ``e_Omega`` from `tracking_errors`. The closed loop is exponentially stable
    for ``Psi(R, Rd) < 2`` (almost globally: the set ``Psi = 2`` of 180-degree
    errors is where ``e_R = 0`` with ``R != Rd``). A pure function: `jit`,
    `vmap` and `grad` (also with respect to the gains) go through it.

    **Arguments:**

    - `gains`: a `GeometricGains`.
    - `body`: the `RigidBody` (its inertia ``J``).
    - `R`: attitude, shape `(..., 3, 3)`.
    - `Omega`: body angular velocity, shape `(..., 3)`.
    - `Rd`: desired attitude, shape `(..., 3, 3)`.
    - `Omega_d`: desired angular velocity, shape `(..., 3)`.
    - `dOmega_d`: its time derivative, shape `(..., 3)`.

    **Returns:** the body torque ``M``, shape `(..., 3)`.

    References: T. Lee, M. Leok, N. H. McClamroch, "Geometric tracking control
    of a quadrotor UAV on SE(3)", CDC 2010, eq. (16) (attitude part).
    """
    _check_gains_body(gains, body)
    R = _prep(R, "R", (3, 3))
    Omega = _prep(Omega, "Omega", (3,))
    Rd = _prep(Rd, "Rd", (3, 3))
    Omega_d = _prep(Omega_d, "Omega_d", (3,))
    dOmega_d = _prep(dOmega_d, "dOmega_d", (3,))
    return _geometric_torque(gains, body, R, Omega, Rd, Omega_d, dOmega_d)


# --------------------------------------------------------------------------
# Controllers (pluggable into the tracking scene)
# --------------------------------------------------------------------------


class AbstractController(eqx.Module):
    """A tracking controller: ``M = controller(t, body, R, Omega, Rd, Omega_d, dOmega_d, memory)``.

    Controllers with a discrete memory (hybrid controllers) set
    ``memory_size > 0`` and implement `init_memory` and `update_memory`; the
    memory rides in the scene state (``y.x[3:]``, zero derivative) and is
    updated after every step (`Scene.jump`).
    """

    memory_size: ClassVar[int] = 0

    @abc.abstractmethod
    def __call__(self, t, body, R, Omega, Rd, Omega_d, dOmega_d, memory=None) -> Vec3:
        """Body torque, shape `(3,)`."""

    def angular_acceleration(
        self, t, body: RigidBody, R, Omega, Rd, Omega_d, dOmega_d, memory=None
    ) -> Vec3:
        """The closed loop's ``Omega' = J^-1 (M - Omega x J Omega)`` with this torque ``M``.

        What a `Tracking` scene integrates (its `Tracking.torque` unchanged). A
        controller whose torque cancels terms of Euler's equations overrides it with
        the closed form (`GeometricController`, `QuaternionController`: their
        feedforward's ``Omega x J Omega``, unless a subclass changed the torque); the
        default forms ``M`` and applies `RigidBody.euler_rhs`.
        """
        return body.euler_rhs(Omega, self(t, body, R, Omega, Rd, Omega_d, dOmega_d, memory))

    def init_memory(self, R: Rot, Rd: Rot) -> Array:
        """Initial memory for the initial attitudes, shape `(memory_size,)`."""
        return jnp.zeros(R.shape[:-2] + (self.memory_size,), R.dtype)

    def update_memory(self, R: Rot, Rd: Rot, memory: Array) -> Array:
        """The memory after a step that ended at ``(R, Rd)``; identity by default."""
        return memory

    def observe(self, R: Rot, Rd: Rot, memory: Array) -> dict[str, Array]:
        """Extra quantities to save in a `Trajectory` (none by default)."""
        return {}


class GeometricController(AbstractController):
    """`geometric_torque` as a pluggable controller (no memory).

    A `Tracking` scene integrates its closed loop with the gyroscopic terms cancelled
    (`angular_acceleration`: the torque's feedforward adds ``Omega x J Omega``, which
    Euler's equations subtract), the same to round-off in fewer operations; the saved
    ``M`` is the torque.

    **Arguments:**

    - `gains`: a `GeometricGains`.
    """

    gains: GeometricGains

    def __check_init__(self):
        if not isinstance(self.gains, GeometricGains):
            raise TypeError(f"gains must be a GeometricGains, got {type(self.gains).__name__}")

    def __call__(self, t, body, R, Omega, Rd, Omega_d, dOmega_d, memory=None):
        return _geometric_torque(self.gains, body, R, Omega, Rd, Omega_d, dOmega_d)

    def angular_acceleration(self, t, body, R, Omega, Rd, Omega_d, dOmega_d, memory=None):
        if type(self).__call__ is not GeometricController.__call__:  # a subclass's torque
            return super().angular_acceleration(t, body, R, Omega, Rd, Omega_d, dOmega_d, memory)
        feedback, a, b = _geometric_feedback(self.gains, R, Omega, Rd, Omega_d, dOmega_d)
        return _closed_loop(body, feedback, Omega, a, b)


def _align(q: Array, q_ref: Array) -> Array:
    """``q`` or ``-q``, whichever is closer to ``q_ref`` (continuous path lifting)."""
    return jnp.where((_dot(q, q_ref) < 0)[..., None], -q, q)


class QuaternionController(AbstractController):
    """Quaternion feedback with (or without) hysteresis: robust global tracking.

    With the error quaternion ``q = (eta, eps)`` of ``Rd^T R``, lifted
    continuously along the trajectory (``q`` is chosen among ``+-q`` to be
    closest to the previous one), and a logic variable ``h in {-1, 1}``:

        M = -k_q h eps - k_Omega e_Omega + Omega x J Omega
            - J (hat(Omega) R^T Rd Omega_d - R^T Rd dOmega_d)

    and ``h`` flips when ``h eta < -delta`` (hysteresis). The Lyapunov function
    ``2 k_q (1 - h eta) + 1/2 e_Omega . J e_Omega`` decreases along flows.
    Without hysteresis (``hysteresis=False``) ``h = 1`` forever: the classical
    continuous quaternion feedback, which *unwinds* (drives ``q`` to ``+1``
    even when ``-1``, the same attitude, is nearer, rotating the long way).
    ``delta = 0`` gives (up to one step of lag) the memoryless discontinuous
    law ``h = sign(eta)``, which is not robust to measurement noise.

    Memory (``memory_size = 5``): ``[h, q_lift]``, initialised to
    ``[1, to_quat(Rd0^T R0)]`` (so ``eta >= 0`` at the start).

    **Arguments:**

    - `k_q`: attitude gain (> 0), scalar or 3-vector. Near the target
      ``eps ~ angle / 2``, so ``k_q = 2 k_R`` matches a geometric gain ``k_R``.
    - `k_Omega`: angular-velocity gain (> 0), scalar or 3-vector.
    - `delta`: hysteresis half-width in ``[0, 1)``.
    - `hysteresis`: switch ``h`` (``True``) or keep ``h = 1`` (``False``).

    References: C. G. Mayhew, R. G. Sanfelice, A. R. Teel, "Quaternion-based
    hybrid control for robust global attitude tracking", IEEE TAC 56(11), 2011;
    and "On path-lifting mechanisms and unwinding in quaternion-based attitude
    control", IEEE TAC 58(5), 2013.
    """

    k_q: Array
    k_Omega: Array
    delta: Array
    hysteresis: bool = eqx.field(static=True)
    memory_size: ClassVar[int] = 5

    def __init__(self, k_q: ArrayLike, k_Omega: ArrayLike, delta=0.2, hysteresis: bool = True):
        self.k_q = _check_gain(k_q, "QuaternionController.k_q")
        self.k_Omega = _check_gain(k_Omega, "QuaternionController.k_Omega")
        d = _as_float(delta)
        if d.shape != ():
            raise ValueError(f"delta must be a scalar, got shape {d.shape}")
        if _is_concrete(d) and not (0.0 <= float(d) < 1.0):
            raise ValueError(f"delta must be in [0, 1), got {float(d)}")
        self.delta = d
        self.hysteresis = bool(hysteresis)

    def _quat(self, R, Rd, memory):
        return _align(_to_quat(_mm(_mT(Rd), R)), memory[..., 1:5])

    def _feedback(self, R, Omega, Rd, Omega_d, dOmega_d, memory):
        """``(-k_q h q_v - k_Omega e_Omega, a, b)`` (`_feedforward`'s ``a``, ``b``)."""
        if memory is None:
            raise ValueError("QuaternionController needs its memory [h, q_lift] (shape (5,))")
        h = memory[..., 0:1]
        q = self._quat(R, Rd, memory)
        _, (a, b) = _errors_and_rates(R, Rd, (Omega_d, dOmega_d))
        return -self.k_q * h * q[..., 1:] - self.k_Omega * (Omega - a), a, b

    def __call__(self, t, body, R, Omega, Rd, Omega_d, dOmega_d, memory=None):
        feedback, a, b = self._feedback(R, Omega, Rd, Omega_d, dOmega_d, memory)
        return feedback + _feedforward(body, Omega, a, b)

    def angular_acceleration(self, t, body, R, Omega, Rd, Omega_d, dOmega_d, memory=None):
        if type(self).__call__ is not QuaternionController.__call__:  # a subclass's torque
            return super().angular_acceleration(t, body, R, Omega, Rd, Omega_d, dOmega_d, memory)
        feedback, a, b = self._feedback(R, Omega, Rd, Omega_d, dOmega_d, memory)
        return _closed_loop(body, feedback, Omega, a, b)

    def init_memory(self, R, Rd):
        q = _to_quat(_mm(_mT(Rd), R))
        return jnp.concatenate([jnp.ones_like(q[..., :1]), q], -1)

    def update_memory(self, R, Rd, memory):
        h = memory[..., 0:1]
        q = self._quat(R, Rd, memory)
        if self.hysteresis:
            h = jnp.where(h * q[..., 0:1] < -self.delta, -h, h)
        return jnp.concatenate([h, q], -1)

    def observe(self, R, Rd, memory):
        return {"h": memory[..., 0], "q_lift": memory[..., 1:5]}


# --------------------------------------------------------------------------
# References t -> (Omega_d(t), dOmega_d(t))
# --------------------------------------------------------------------------

Reference = Callable[[Scalar], tuple[Vec3, Vec3]]


class AbstractReference(eqx.Module):
    """A desired body angular velocity: ``reference(t) -> (Omega_d(t), dOmega_d(t))``.

    Any function with that signature works as a reference; these modules keep
    their parameters as arrays (traceable: `vmap`/`grad` through them).
    """

    @abc.abstractmethod
    def __call__(self, t: Scalar) -> tuple[Vec3, Vec3]: ...


def _vec_param(value, name: str, allow_scalar: bool = True) -> Array:
    v = _as_float(value)
    if v.shape not in (((), (3,)) if allow_scalar else ((3,),)):
        want = "a scalar or a 3-vector" if allow_scalar else "a 3-vector"
        raise ValueError(f"{name} must be {want}, got shape {v.shape}")
    if _is_concrete(v) and not np.all(np.isfinite(np.asarray(v))):
        raise ValueError(f"{name} must be finite")
    return v


class ConstantRate(AbstractReference):
    """Constant desired rate: ``Omega_d(t) = w``, ``dOmega_d = 0`` (``w = 0``: regulation).

    **Arguments:**

    - `rate`: ``w``, shape `(3,)` (default zero).
    """

    rate: Array

    def __init__(self, rate: ArrayLike = (0.0, 0.0, 0.0)):
        self.rate = _vec_param(rate, "rate", allow_scalar=False)

    def __call__(self, t):
        t = jnp.asarray(t)
        w = jnp.broadcast_to(self.rate, t.shape + (3,)).astype(jnp.result_type(t, self.rate))
        return w, jnp.zeros_like(w)


class SinusoidalRate(AbstractReference):
    """Sinusoidal desired rate on each body axis.

    ``Omega_d,i(t) = A_i sin(2 pi f t + phi_i)``,
    ``dOmega_d,i(t) = 2 pi f A_i cos(2 pi f t + phi_i)``.

    The default is the profile of the seed scenario (ours: the MATLAB seed's
    ``get_desired_angular_velocity.m`` is not available): ``A = 0.5`` rad/s on
    every axis, ``f = 0.2`` Hz (period 5 s) and phases ``(0, 2 pi/3, 4 pi/3)``
    (a balanced three-phase profile, so the reference turns about all three axes).

    **Arguments:**

    - `amplitude`: ``A`` in rad/s, scalar or shape `(3,)`.
    - `frequency`: ``f`` in Hz, scalar or shape `(3,)`.
    - `phase`: ``phi`` in rad, scalar or shape `(3,)`.
    """

    amplitude: Array
    frequency: Array
    phase: Array

    def __init__(
        self,
        amplitude: ArrayLike = 0.5,
        frequency: ArrayLike = 0.2,
        phase: ArrayLike = (0.0, 2 * math.pi / 3, 4 * math.pi / 3),
    ):
        self.amplitude = _vec_param(amplitude, "amplitude")
        self.frequency = _vec_param(frequency, "frequency")
        self.phase = _vec_param(phase, "phase")

    def __call__(self, t):
        t = jnp.asarray(t)[..., None]
        w = 2 * jnp.pi * self.frequency
        arg = w * t + self.phase
        return self.amplitude * jnp.sin(arg), self.amplitude * w * jnp.cos(arg)


class ConingRate(AbstractReference):
    """Coning (precession) rate: the body rates of a torque-free symmetric top.

    ``Omega_d(t) = (a cos(nu t), a sin(nu t), s)``,
    ``dOmega_d(t) = (-a nu sin(nu t), a nu cos(nu t), 0)``.

    A spin ``s`` about the body 3-axis with a transverse rate of magnitude
    ``a`` that turns at ``nu`` in the body: the desired attitude cones about a
    fixed direction, tumbling through every orientation about it. For an
    axisymmetric body (``J1 = J2``) with ``nu = (J1 - J3) s / J1`` this is a
    torque-free motion, so the feedforward torque vanishes.

    **Arguments:**

    - `amplitude`: ``a`` in rad/s.
    - `rate`: ``nu`` in rad/s.
    - `spin`: ``s`` in rad/s.
    """

    amplitude: Array
    rate: Array
    spin: Array

    def __init__(self, amplitude: ArrayLike = 1.0, rate: ArrayLike = 0.5, spin: ArrayLike = 2.0):
        for value, name in ((amplitude, "amplitude"), (rate, "rate"), (spin, "spin")):
            v = _as_float(value)
            if v.shape != ():
                raise ValueError(f"{name} must be a scalar, got shape {v.shape}")
        self.amplitude = _as_float(amplitude)
        self.rate = _as_float(rate)
        self.spin = _as_float(spin)

    def __call__(self, t):
        t = jnp.asarray(t)
        c, s = jnp.cos(self.rate * t), jnp.sin(self.rate * t)
        a, nu = self.amplitude, self.rate
        spin = jnp.broadcast_to(self.spin, c.shape).astype(c.dtype)
        w = jnp.stack([a * c, a * s, spin], -1)
        dw = jnp.stack([-a * nu * s, a * nu * c, jnp.zeros_like(c)], -1)
        return w, dw


def _scalar_param(value, name: str, positive: bool = False) -> Array:
    v = _as_float(value)
    if v.shape != ():
        raise ValueError(f"{name} must be a scalar, got shape {v.shape}")
    if _is_concrete(v):
        x = float(np.asarray(v, np.float64))
        if not math.isfinite(x) or (positive and x <= 0):
            want = "positive and finite" if positive else "finite"
            raise ValueError(f"{name} must be {want}, got {x}")
    return v


class SlewReference(AbstractReference):
    """A rest-to-rest slew about a fixed body axis: ``Rd0 -> Rd0 exp(angle hat(n))``.

    With ``n = axis / |axis|``, ``tau = t / T`` (``T`` the duration) and the
    degree-7 profile ``s(tau) = 35 tau^4 - 84 tau^5 + 70 tau^6 - 20 tau^7``
    (``s(0) = 0``, ``s(1) = 1``; its first three derivatives vanish at both ends):

    ``Omega_d(t) = angle s'(t) n`` with ``s'(t) = 140 tau^3 (1 - tau)^3 / T``,
    ``dOmega_d(t) = angle s''(t) n`` with
    ``s''(t) = 420 tau^2 (1 - tau)^2 (1 - 2 tau) / T^2``,

    on ``0 <= t <= T``, and ``Omega_d = dOmega_d = 0`` before and after (hold).
    Rate, acceleration and jerk are zero at both ends, so ``Omega_d`` and
    ``dOmega_d`` are continuous in ``t`` (and so is the feedforward torque and
    its derivative). Every ``Omega_d(t)`` is parallel to ``n``, so the
    reference attitude (``Rd' = Rd hat(Omega_d)``) has the closed form
    ``Rd(t) = Rd0 exp(angle s(t) hat(n))``: it turns by ``angle`` about the
    body axis ``n`` and holds ``Rd0 exp(angle hat(n))`` from ``t = T`` on.

    **Arguments:**

    - `axis`: the axis of the slew in the reference's body frame, a nonzero
      3-vector (normalised here).
    - `angle`: the slew angle in rad (any finite value; negative turns the
      other way, more than ``pi`` goes the long way round).
    - `duration`: ``T`` in s (positive, finite).

    Arguments are checked when their values are concrete (``ValueError``
    naming the argument); the fields are arrays, so `jax.vmap` and `jax.grad`
    over ``angle`` and ``duration`` work.

    References: L. Biagiotti, C. Melchiorri, "Trajectory Planning for Automatic
    Machines and Robots", Springer 2008 (the degree-7 polynomial profile).
    """

    axis: Array
    angle: Array
    duration: Array

    def __init__(self, axis: ArrayLike, angle: ArrayLike, duration: ArrayLike):
        n = _vec_param(axis, "axis", allow_scalar=False)
        if _is_concrete(n):
            nn = np.asarray(n, np.float64)
            norm = float(np.linalg.norm(nn))
            if not norm > 0:
                raise ValueError(f"axis must be a nonzero 3-vector, got {nn}")
            self.axis = jax.device_put(np.asarray(nn / norm, n.dtype))
        else:
            self.axis = n / jnp.sqrt(_dot(n, n))[..., None]
        self.angle = _scalar_param(angle, "angle")
        self.duration = _scalar_param(duration, "duration", positive=True)

    def __call__(self, t):
        t = jnp.asarray(t)
        T = self.duration
        tau = jnp.clip(t / T, 0.0, 1.0)  # the polynomials vanish at both ends: hold
        u = tau * (1.0 - tau)
        ds = 140.0 * u**3 / T
        dds = 420.0 * u**2 * (1.0 - 2.0 * tau) / T**2
        return (self.angle * ds)[..., None] * self.axis, (self.angle * dds)[..., None] * self.axis
