"""The quadrotor on SE(3): Lee's geometric tracking controller, continuous or sampled.

Lee, Leok & McClamroch (CDC 2010) model a quadrotor as a rigid body of mass
``m`` and inertia ``J`` with position ``x``, velocity ``v``, attitude ``R`` and
body rate ``Omega``, driven by a total thrust ``f`` along ``-R e3`` and a body
moment ``M`` (``e3`` points *down*):

    x' = v,   m v' = m g e3 - f R e3,   R' = R hat(Omega),   J Omega' + Omega x J Omega = M.

Their controller tracks a position ``x_d(t)`` and a heading ``b1_d(t)``: the
position loop asks for the force ``-A`` (``f = -A . R e3``) and the attitude
``Rc`` whose third axis is ``-A / |A|``; the attitude loop is the geometric
controller of `so3jax.geometric_torque` tracking ``Rc`` with the rates
``Omega_c``, ``dOmega_c`` of ``Rc`` along the closed loop. A reference is a plain
function ``t -> (x_d(t), b1_d(t))``: every derivative the controller needs
(``x_d`` up to the 4th, ``b1_d`` up to the 2nd) is taken by `jax.jvp`.

The state lives on ``SO(3) x R^9``: ``y.R`` is ``R[None]`` and
``y.x = [Omega, x, v]``. With ``control_period = T`` the controller is sampled
and held (zero-order hold, as flight software runs it): ``y.x`` also carries the
held ``(f, M)`` and a step counter ``c``, all with zero derivative; the scene's
`jump` (after every step) evaluates the controller when ``c`` reaches ``T / dt``
steps and resets ``c``. `simulate` tells the scene its step through
`Scene.for_step`, which also checks that ``dt`` divides ``T`` and takes the
first sample from the initial state.

The plant may be more than the controller's model (`quadrotor`'s ``rotors``,
``drag``, ``wind``): the commanded ``(f, M)`` goes through four rotors
(`so3jax.Rotors`: allocation by Lee et al.'s eq. (1), per-rotor thrust limits,
an optional first-order lag whose four thrusts join ``y.x`` at its end), and
the body feels a linear drag ``-R diag(d) R^T (v - w(t))``. The controller keeps
its nominal model; without these options the scene is the one above.

References: T. Lee, M. Leok, N. H. McClamroch, "Geometric tracking control of a
quadrotor UAV on SE(3)", CDC 2010 (and the FDCL's public reference code,
fdcl-gwu); S. Cheng et al., "DiffTune: auto-tuning through auto-differentiation",
IEEE T-RO 2024 (the tuning example).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._actuators import Rotors
from ._control import _check_gain, _geometric_torque
from ._dynamics import RigidBody
from ._repr import module_repr
from ._scene import Scene, check_rotation
from ._scenes import _as_body, _cast_floats, _check_reference, _steps_per_hold
from ._sensors import SensorNoise, check_noise
from ._so3 import _as_float, _cross, _dot, _is_concrete, _mm, _mT, _mv, _to_dtype, _vee
from ._state import LieState, LieTangent
from ._trajectory import COMMAND_UNDEFINED, OK
from ._types import Array, ArrayLike

#: Vehicle and gains of DiffTune's quadrotor example (Cheng et al., T-RO 2024),
#: the vehicle of Lee, Leok & McClamroch (CDC 2010).
DIFFTUNE_MASS = 4.34
DIFFTUNE_INERTIA = (0.0820, 0.0845, 0.1377)
DIFFTUNE_GAINS = (16.0, 5.6, 8.81, 2.54)  # k_x, k_v, k_R, k_Omega (each per axis)
#: Gains of Lee, Leok & McClamroch's numerical example (CDC 2010): ``k_x = 16 m``,
#: ``k_v = 5.6 m`` (``m = 4.34`` kg: 69.44 and 24.304), ``k_R = 8.81``, ``k_Omega = 2.54``.
PAPER_GAINS = (16.0 * DIFFTUNE_MASS, 5.6 * DIFFTUNE_MASS, 8.81, 2.54)
#: Initial attitude of the paper's recovery case (nearly upside down: 178 degrees about e1).
RECOVERY_R0 = ((1.0, 0.0, 0.0), (0.0, -0.9995, -0.0314), (0.0, 0.0314, -0.9995))


# --------------------------------------------------------------------------
# Gains, vehicle
# --------------------------------------------------------------------------


class QuadrotorGains(eqx.Module):
    """Gains of Lee's quadrotor controller: position, velocity, attitude, rate, integrals.

    ``A = -k_x e_x - k_v e_v - k_i sat(e_i) - m g e3 + m x_d''``,
    ``M = -k_R e_R - k_Omega e_Omega - k_I sat(e_I) + ...``. Each gain is a
    scalar or a 3-vector (one value per axis: inertial axes for ``k_x``, ``k_v``,
    ``k_i``, body axes for ``k_R``, ``k_Omega``, ``k_I``). The fields are arrays:
    `jax.grad` with respect to a `QuadrotorGains` works, and
    ``jax.vmap(QuadrotorGains)(...)`` builds a batch.

    **Integral action** (off by default) follows Goodarzi, Lee & Lee (ECC 2013):
    a position integral ``e_i`` and an attitude integral ``e_I`` with

        e_i' = e_v + c1 e_x,      e_I' = e_Omega + c2 e_R,

    entering the controller through the saturation ``sat(e) = clip(e, -sigma,
    sigma)`` (per axis; their ``sat_sigma``). Their derivative enters ``A'`` and
    ``A''`` (``-k_i sat(e_i)'``, ``-k_i sat(e_i)''`` with ``e_i'' = e_v' + c1
    e_v``), so ``Omega_c`` and ``dOmega_c`` stay the rates of ``Rc``. The clamp is
    also an anti-windup: the integrals themselves stay in ``[-sigma, sigma]``, as
    in the FDCL's uav_simulator (fdcl-gwu), which clamps its integral state. With
    ``k_i = k_I = 0`` (concrete zeros, the default) the six integral fields are
    ``None`` and the controller is Lee's, the same program as without them; a
    `quadrotor` scene built with nonzero (or traced) ``k_i``, ``k_I`` carries the
    integrals in its state (see `quadrotor`).

    **Arguments:**

    - `k_x`: position gain (>= 0, finite), shape `()` or `(3,)`.
    - `k_v`: velocity gain (>= 0, finite), shape `()` or `(3,)`.
    - `k_R`: attitude gain (>= 0, finite), shape `()` or `(3,)`.
    - `k_Omega`: body-rate gain (>= 0, finite), shape `()` or `(3,)`.
    - `k_i`: position integral gain in N/m (>= 0, finite), shape `()` or `(3,)`.
    - `k_I`: attitude integral gain in N m/rad (>= 0, finite), shape `()` or `(3,)`.
    - `c1`: weight of ``e_x`` in ``e_i'``, in 1/s (>= 0, finite), shape `()`.
    - `c2`: weight of ``e_R`` in ``e_I'``, in 1/s (>= 0, finite), shape `()`.
    - `sigma_i`: clamp of ``e_i`` in m (> 0; ``inf``: none), shape `()` or `(3,)`.
    - `sigma_I`: clamp of ``e_I`` in rad (> 0; ``inf``: none), shape `()` or `(3,)`.

    Negative or non-finite gains (and clamps that are not positive) raise
    ``ValueError`` naming the argument when the values are concrete (under
    `jit`/`vmap` they are not checked).

    References: T. Lee, M. Leok, N. H. McClamroch, CDC 2010, eqs. (12), (16);
    F. Goodarzi, D. Lee, T. Lee, "Geometric nonlinear PID control of a quadrotor
    UAV on SE(3)", ECC 2013 (the integral terms ``e_i``, ``e_I`` and ``sat_sigma``).
    """

    k_x: Array
    k_v: Array
    k_R: Array
    k_Omega: Array
    k_i: Array | None = None
    k_I: Array | None = None
    c1: Array | None = None
    c2: Array | None = None
    sigma_i: Array | None = None
    sigma_I: Array | None = None

    __repr__ = module_repr

    def __init__(
        self,
        k_x: ArrayLike,
        k_v: ArrayLike,
        k_R: ArrayLike,
        k_Omega: ArrayLike,
        k_i: ArrayLike = 0.0,
        k_I: ArrayLike = 0.0,
        c1: ArrayLike = 1.0,
        c2: ArrayLike = 1.0,
        sigma_i: ArrayLike = 1.0,
        sigma_I: ArrayLike = 1.0,
    ):
        self.k_x = _check_gain(k_x, "QuadrotorGains.k_x")
        self.k_v = _check_gain(k_v, "QuadrotorGains.k_v")
        self.k_R = _check_gain(k_R, "QuadrotorGains.k_R")
        self.k_Omega = _check_gain(k_Omega, "QuadrotorGains.k_Omega")
        off = _is_zero(k_i) and _is_zero(k_I)  # before conversion: under jit it stages
        k_i = _check_gain(k_i, "QuadrotorGains.k_i")
        k_I = _check_gain(k_I, "QuadrotorGains.k_I")
        c1 = _check_scalar(c1, "QuadrotorGains.c1", positive=False)
        c2 = _check_scalar(c2, "QuadrotorGains.c2", positive=False)
        sigma_i = _check_clamp(sigma_i, "QuadrotorGains.sigma_i")
        sigma_I = _check_clamp(sigma_I, "QuadrotorGains.sigma_I")
        if not off:
            self.k_i, self.k_I, self.c1, self.c2 = k_i, k_I, c1, c2
            self.sigma_i, self.sigma_I = sigma_i, sigma_I

    @property
    def integral(self) -> bool:
        """Whether the gains have integral action (``k_i``, ``k_I`` not both zero)."""
        return self.k_i is not None


def _is_zero(k) -> bool:
    """``k`` (as given) is concrete and zero (a traced gain counts as nonzero: it may be)."""
    return _is_concrete(k) and not np.any(np.asarray(k))


def _check_clamp(value, name: str) -> Array:
    """A clamp ``sigma > 0`` (``inf`` allowed: no clamp), shape `()` or `(3,)`."""
    s = _as_float(value)
    if s.shape not in ((), (3,)):
        raise ValueError(f"{name} must be a scalar or a 3-vector, got shape {s.shape}")
    if _is_concrete(s):
        sn = np.asarray(s, dtype=np.float64)
        if np.any(np.isnan(sn)) or np.any(sn <= 0):
            raise ValueError(f"{name} must be positive (inf: no clamp), got {sn}")
    return s


class QuadrotorVehicle(eqx.Module):
    """Mass, inertia and gravity of a quadrotor.

    **Fields:**

    - `mass`: ``m`` in kg, shape `()`.
    - `body`: a `RigidBody` (the inertia ``J``).
    - `g`: gravitational acceleration in m/s^2 (along ``+e3``, down), shape `()`.
    """

    mass: Array
    body: RigidBody
    g: Array

    __repr__ = module_repr


def _check_scalar(value, name: str, positive: bool) -> Array:
    a = _as_float(value)
    if a.shape != ():
        raise ValueError(f"{name} must be a scalar, got shape {a.shape}")
    if _is_concrete(a):
        v = float(np.asarray(a))
        if not math.isfinite(v) or (v <= 0 if positive else v < 0):
            want = "positive and finite" if positive else ">= 0 and finite"
            raise ValueError(f"{name} must be {want}, got {v}")
    return a


# --------------------------------------------------------------------------
# The controller
# --------------------------------------------------------------------------


class QuadrotorControl(NamedTuple):
    """What Lee's controller computes at one state (each leaf may carry batch axes).

    - `f`: total thrust, shape `()`; `M`: body moment, shape `(3,)`.
    - `Rc`: commanded attitude ``[b1c, b2c, b3c]``; `Omega_c`, `dOmega_c`: its body
      rate and the rate's derivative along the closed loop, shape `(3,)`.
    - `x_d`: desired position; `e_x`, `e_v`: position and velocity errors.
    - `e_R`, `e_Omega`: attitude and rate errors against ``Rc``; `Psi`:
      ``1/2 tr(I - Rc^T R)``.
    """

    f: Array
    M: Array
    Rc: Array
    Omega_c: Array
    dOmega_c: Array
    x_d: Array
    e_x: Array
    e_v: Array
    e_R: Array
    e_Omega: Array
    Psi: Array


def _e3(dtype):
    return jnp.asarray([0.0, 0.0, 1.0], dtype)


def _time_derivatives(fn, t, order: int):
    """``[fn(t), fn'(t), ..., fn^(order)(t)]`` by nested `jax.jvp` in ``t``."""

    def up(g):
        def dg(s):
            out, tan = jax.jvp(g, (s,), (jnp.ones_like(s),))
            return out + [tan[-1]]

        return dg

    g = lambda s: [fn(s)]  # noqa: E731
    for _ in range(order):
        g = up(g)
    return g(t)


def _unit_2(a, a1, a2, floor2=None):
    """``u = a/|a|`` and its first two time derivatives from those of ``a``.

    With ``n = |a|``: ``n' = u . a'``, ``u' = (a' - u n') / n``,
    ``n'' = u' . a' + u . a''``, ``u'' = (a'' - 2 u' n' - u n'') / n``.
    Where ``|a|^2`` is below ``floor2`` (default: the dtype's smallest normal
    number) the direction is undefined and ``u`` and its derivatives are NaN, so
    the run's status reports it (`Status`, code 20) instead of going on with a
    zero vector.
    """
    n2 = _dot(a, a)
    small = n2 < (jnp.finfo(a.dtype).tiny if floor2 is None else floor2)
    inv = jnp.where(small, jnp.nan, 1.0 / jnp.sqrt(jnp.where(small, 1.0, n2)))[..., None]
    u = a * inv
    n1 = _dot(u, a1)[..., None]
    u1 = (a1 - u * n1) * inv
    nn2 = (_dot(u1, a1) + _dot(u, a2))[..., None]
    u2 = (a2 - 2.0 * u1 * n1 - u * nn2) * inv
    return u, u1, u2


def _commanded_attitude(A, A1, A2, b, b1, b2):
    """``Rc = [b1c, b2c, b3c]`` and its first two time derivatives.

    ``b3c = -A/|A|``, ``b2c = b3c x b1_d / |b3c x b1_d|``, ``b1c = b2c x b3c``
    (Lee, Leok & McClamroch 2010, after eq. (14)); the derivatives by the
    product rule from those of ``A`` and ``b1_d`` (`_unit_2` for the norms).
    """
    b3, b3_1, b3_2 = _unit_2(-A, -A1, -A2)
    c = _cross(b3, b)
    c1 = _cross(b3_1, b) + _cross(b3, b1)
    c2 = _cross(b3_2, b) + 2.0 * _cross(b3_1, b1) + _cross(b3, b2)
    # b1_d parallel to b3c (to a few ulps): b2c is undefined, and so is Rc.
    floor2 = (16 * jnp.finfo(c.dtype).eps) ** 2 * _dot(b, b)
    b2c, b2c_1, b2c_2 = _unit_2(c, c1, c2, floor2)
    b1c = _cross(b2c, b3)
    b1c_1 = _cross(b2c_1, b3) + _cross(b2c, b3_1)
    b1c_2 = _cross(b2c_2, b3) + 2.0 * _cross(b2c_1, b3_1) + _cross(b2c, b3_2)

    def cols(x, y, z):
        return jnp.stack([x, y, z], axis=-1)

    return cols(b1c, b2c, b3), cols(b1c_1, b2c_1, b3_1), cols(b1c_2, b2c_2, b3_2)


def quadrotor_control(
    gains: QuadrotorGains,
    vehicle: QuadrotorVehicle,
    t: Array,
    x: Array,
    v: Array,
    R: Array,
    Omega: Array,
    reference: Callable,
    e_i: Array | None = None,
    e_I: Array | None = None,
) -> QuadrotorControl:
    """Lee's geometric tracking controller on SE(3), as a pure function.

    Position loop: ``e_x = x - x_d``, ``e_v = v - x_d'``,
    ``A = -k_x e_x - k_v e_v - m g e3 + m x_d''``, ``f = -A . R e3``,
    ``Rc = [b1c, b2c, b3c]`` with ``b3c = -A/|A|``,
    ``b2c = b3c x b1_d / |b3c x b1_d|``, ``b1c = b2c x b3c``.

    Attitude loop (`geometric_torque` tracking ``Rc``):
    ``M = -k_R e_R - k_Omega e_Omega + Omega x J Omega
    - J (hat(Omega) R^T Rc Omega_c - R^T Rc dOmega_c)``, with
    ``hat(Omega_c) = Rc^T Rc'`` and ``dOmega_c = Omega_c'``.

    ``Rc'`` and ``Rc''`` are the exact time derivatives along the *continuous*
    closed loop (with ``f = -A . R e3`` applied, whatever is held), in three parts:

    - the reference's derivatives (``x_d`` to the 4th, ``b1_d`` to the 2nd) by
      nested `jax.jvp` in ``t``: any differentiable function of time works;
    - ``A'`` and ``A''`` by the paper's closed-loop formulas (as in the FDCL's
      code): ``e_v' = g e3 - f R e3 / m - x_d''``,
      ``A' = -k_x e_v - k_v e_v' + m x_d'''``,
      ``f' = -A' . R e3 - A . R hat(Omega) e3``,
      ``e_v'' = -(f' R e3 + f R hat(Omega) e3) / m - x_d'''``,
      ``A'' = -k_x e_v' - k_v e_v'' + m x_d''''``; no ``Omega'`` appears, so
      there is no loop through ``M``;
    - ``Rc'``, ``Rc''`` by the product rule through the unit vectors and cross
      products that build ``Rc`` (about a tenth of the operations of nested
      `jax.jvp` of the map ``(A, b1_d) -> Rc``, which we used at first and
      which agrees to round-off; this is the controller's inner loop).

    With integral action (``gains.integral``; Goodarzi, Lee & Lee, ECC 2013),
    ``A`` gains ``-k_i sat(e_i)``, ``A'`` gains ``-k_i sat(e_i)'`` with
    ``sat(e_i)' = e_v + c1 e_x`` where ``|e_i| < sigma_i`` (0 where clamped),
    ``A''`` gains ``-k_i sat(e_i)''`` with ``sat(e_i)'' = e_v' + c1 e_v`` (0
    where clamped), and ``M`` gains ``-k_I sat(e_I)``; ``sat`` clips each axis to
    ``[-sigma, sigma]`` (see `QuadrotorGains`).

    **Arguments:**

    - `gains`: a `QuadrotorGains`.
    - `vehicle`: a `QuadrotorVehicle` (mass, inertia, g).
    - `t`: time, shape `()`.
    - `x`, `v`: position and velocity (inertial frame, ``e3`` down), shape `(3,)`.
    - `R`: attitude, shape `(3, 3)`; `Omega`: body rate, shape `(3,)`.
    - `reference`: a function ``t -> (x_d(t), b1_d(t))``, both shape `(3,)`.
    - `e_i`, `e_I`: the position and attitude integrals, shape `(3,)` (default:
      zero), for gains with integral action only.

    **Returns:** a `QuadrotorControl` (``f``, ``M``, ``Rc``, ``Omega_c``,
    ``dOmega_c``, ``x_d`` and the tracking errors).

    References: T. Lee, M. Leok, N. H. McClamroch, "Geometric tracking control
    of a quadrotor UAV on SE(3)", CDC 2010, eqs. (12)-(16); the FDCL's
    reference code (fdcl-gwu) for the derivatives of ``A``; F. Goodarzi, D. Lee,
    T. Lee, "Geometric nonlinear PID control of a quadrotor UAV on SE(3)", ECC
    2013 (the integral terms).
    """
    if gains.integral:
        e_i = jnp.zeros_like(x) if e_i is None else e_i
        e_I = jnp.zeros_like(x) if e_I is None else e_I
    elif e_i is not None or e_I is not None:
        raise ValueError(
            "e_i, e_I need gains with integral action (QuadrotorGains with k_i or k_I nonzero)"
        )
    t = jnp.asarray(t, x.dtype)
    x_d, x1, x2, x3, x4 = _time_derivatives(lambda s: reference(s)[0], t, 4)
    b1d, b1d1, b1d2 = _time_derivatives(lambda s: reference(s)[1], t, 2)
    k_x, k_v = gains.k_x, gains.k_v
    m, g = vehicle.mass, vehicle.g
    e3 = _e3(x.dtype)
    Re3 = _mv(R, e3)
    Re3_1 = _mv(R, _cross(Omega, e3))  # (R e3)' = R hat(Omega) e3
    e_x = x - x_d
    e_v = v - x1
    A = -k_x * e_x - k_v * e_v - m * g * e3 + m * x2
    if gains.integral:  # sat(e_i) and its first two derivatives (0 where clamped)
        inside = jnp.abs(e_i) < gains.sigma_i
        A = A - gains.k_i * jnp.clip(e_i, -gains.sigma_i, gains.sigma_i)
    f = -_dot(A, Re3)
    e_v1 = g * e3 - (f / m)[..., None] * Re3 - x2
    A1 = -k_x * e_v - k_v * e_v1 + m * x3
    if gains.integral:
        A1 = A1 - gains.k_i * jnp.where(inside, e_v + gains.c1 * e_x, 0.0)
    f1 = -_dot(A1, Re3) - _dot(A, Re3_1)
    e_v2 = -(f1[..., None] * Re3 + f[..., None] * Re3_1) / m - x3
    A2 = -k_x * e_v1 - k_v * e_v2 + m * x4
    if gains.integral:
        A2 = A2 - gains.k_i * jnp.where(inside, e_v1 + gains.c1 * e_v, 0.0)

    Rc, Rc1, Rc2 = _commanded_attitude(A, A1, A2, b1d, b1d1, b1d2)
    RcT = _mT(Rc)
    Omega_c = _vee(_mm(RcT, Rc1))
    # d/dt (Rc^T Rc') = Rc'^T Rc' + Rc^T Rc''; the first term is symmetric and `_vee`
    # keeps the skew part only.
    dOmega_c = _vee(_mm(RcT, Rc2))
    M = _geometric_torque(gains, vehicle.body, R, Omega, Rc, Omega_c, dOmega_c)
    if gains.integral:
        M = M - gains.k_I * jnp.clip(e_I, -gains.sigma_I, gains.sigma_I)
    RtRc = _mm(_mT(R), Rc)
    e_R = _vee(_mT(RtRc))
    e_Omega = Omega - _mv(RtRc, Omega_c)
    Psi = 0.5 * (3.0 - jnp.trace(RtRc, axis1=-2, axis2=-1))
    return QuadrotorControl(f, M, Rc, Omega_c, dOmega_c, x_d, e_x, e_v, e_R, e_Omega, Psi)


# --------------------------------------------------------------------------
# References t -> (x_d(t), b1_d(t))
# --------------------------------------------------------------------------


def _e1_like(t):
    t = jnp.asarray(t)
    e1 = jnp.asarray([1.0, 0.0, 0.0], t.dtype if jnp.issubdtype(t.dtype, jnp.floating) else None)
    return jnp.broadcast_to(e1, t.shape + (3,))


def _vec3(value, name: str) -> Array:
    a = _as_float(value)
    if a.shape == ():
        a = jnp.broadcast_to(a, (3,))
    if a.shape != (3,):
        raise ValueError(f"{name} must be a 3-vector, got shape {a.shape}")
    return a


class HoverReference(eqx.Module):
    """Hover: ``x_d(t) = p``, ``b1_d = e1``.

    **Arguments:**

    - `position`: ``p``, shape `(3,)` (default the origin).
    """

    position: Array

    def __init__(self, position: ArrayLike = (0.0, 0.0, 0.0)):
        self.position = _vec3(position, "position")

    def __call__(self, t):
        t = jnp.asarray(t)
        return jnp.broadcast_to(self.position, t.shape + (3,)), _e1_like(t)


class LineReference(eqx.Module):
    """Constant velocity along a line: ``x_d(t) = p + u t``, ``b1_d = e1``.

    **Arguments:**

    - `velocity`: ``u`` in m/s, shape `(3,)`.
    - `start`: ``p``, shape `(3,)`.
    """

    velocity: Array
    start: Array

    def __init__(self, velocity: ArrayLike = (1.0, 0.0, 0.0), start: ArrayLike = (0.0, 0.0, 0.0)):
        self.velocity = _vec3(velocity, "velocity")
        self.start = _vec3(start, "start")

    def __call__(self, t):
        t = jnp.asarray(t)
        return self.start + self.velocity * t[..., None], _e1_like(t)


class CircleReference(eqx.Module):
    """A horizontal circle through the origin (a helix with a climb rate), ``b1_d = e1``.

    ``x_d(t) = (r (1 - cos wt), r sin wt, a sin wt - c t)`` (``e3`` down, so
    ``c > 0`` climbs). DiffTune's example is ``CircleReference(2.0, 1.0, 0.1)``:
    ``x_d = (2 (1 - cos t), 2 sin t, 0.1 sin t)``.

    **Arguments:**

    - `radius`: ``r`` in m.
    - `rate`: ``w`` in rad/s.
    - `vertical`: ``a``, amplitude of a vertical oscillation, in m.
    - `climb`: ``c``, climb rate in m/s (a helix).
    """

    radius: Array
    rate: Array
    vertical: Array
    climb: Array

    def __init__(self, radius=1.0, rate=1.0, vertical=0.0, climb=0.0):
        self.radius = _check_scalar(radius, "radius", positive=True)
        self.rate = _check_scalar(rate, "rate", positive=False)
        self.vertical = _check_scalar(vertical, "vertical", positive=False)
        self.climb = _as_float(climb)

    def __call__(self, t):
        t = jnp.asarray(t)
        wt = self.rate * t
        r = self.radius
        x = jnp.stack(
            [r * (1 - jnp.cos(wt)), r * jnp.sin(wt), self.vertical * jnp.sin(wt) - self.climb * t],
            -1,
        )
        return x, _e1_like(t)


class FigureEightReference(eqx.Module):
    """A horizontal figure-8 (lemniscate of Gerono) through the origin, ``b1_d = e1``.

    ``x_d(t) = (a sin wt, a/2 sin 2wt, 0)``.

    **Arguments:**

    - `size`: ``a`` in m.
    - `rate`: ``w`` in rad/s.
    """

    size: Array
    rate: Array

    def __init__(self, size=1.0, rate=1.0):
        self.size = _check_scalar(size, "size", positive=True)
        self.rate = _check_scalar(rate, "rate", positive=False)

    def __call__(self, t):
        t = jnp.asarray(t)
        wt = self.rate * t
        z = jnp.zeros_like(wt)
        return jnp.stack(
            [self.size * jnp.sin(wt), 0.5 * self.size * jnp.sin(2 * wt), z], -1
        ), _e1_like(t)


def _smoothstep9(u):
    """``S(u) = 126u^5 - 420u^6 + 540u^7 - 315u^8 + 70u^9`` on [0, 1], 0 before, 1 after.

    ``S'``..``S''''`` vanish at both ends, so ``x_d`` built from it has continuous
    derivatives up to the 4th (what the controller uses).
    """
    u = jnp.clip(u, 0.0, 1.0)
    return u**5 * (126 + u * (-420 + u * (540 + u * (-315 + 70 * u))))


class FlipReference(eqx.Module):
    """A flip: one vertical loop about ``e1``, flown fast enough at the top to turn over.

    Hover at the origin until ``start``; then one loop of radius ``r`` in the
    ``y-z`` plane, centred ``r`` above the origin (``e3`` is down):
    ``x_d = (0, r sin phi, -r (1 - cos phi))`` with
    ``phi(t) = 2 pi S((t - start) / duration)`` and ``S`` the degree-9
    smoothstep (speed and its first three derivatives vanish at both ends);
    hover again afterwards; ``b1_d = e1`` throughout. The desired specific force
    ``x_d'' - g e3`` goes once around the origin when ``r phi'^2 > g`` at the top
    (true for the default: ``r phi'^2`` peaks near ``2.7 g``), so the commanded
    thrust axis ``b3c`` turns through a full revolution about ``e1``: the
    vehicle flips once, upside down at the top of the loop.

    **Arguments:**

    - `radius`: ``r`` in m.
    - `duration`: time of the loop in s.
    - `start`: time the loop begins in s.
    """

    radius: Array
    duration: Array
    start: Array

    def __init__(self, radius=1.0, duration=3.0, start=1.0):
        self.radius = _check_scalar(radius, "radius", positive=True)
        self.duration = _check_scalar(duration, "duration", positive=True)
        self.start = _check_scalar(start, "start", positive=False)

    def __call__(self, t):
        t = jnp.asarray(t)
        phi = 2 * jnp.pi * _smoothstep9((t - self.start) / self.duration)
        r = self.radius
        x = jnp.stack([jnp.zeros_like(phi), r * jnp.sin(phi), -r * (1 - jnp.cos(phi))], -1)
        return x, _e1_like(t)


# --------------------------------------------------------------------------
# The scene
# --------------------------------------------------------------------------

_N = 9  # Omega, x, v
_HELD = slice(9, 13)  # f, M (sampled control)
_COUNTER = 13
_N_ROTORS = 4


def _control_of(scene, t, y):
    return scene.control(t, scene.measured(t, y))


def _control_with_position_integral(scene, t, y, e_i):
    """The controller at ``(t, y)`` with the position integral ``e_i`` and no attitude
    integral term (a sample of `Quadrotor._jump_integral`)."""
    R = y.R[..., 0, :, :]
    Omega, x, v = y.x[..., 0:3], y.x[..., 3:6], y.x[..., 6:9]
    return quadrotor_control(
        scene.gains, scene.vehicle, t, x, v, R, Omega, scene.reference, e_i, jnp.zeros_like(e_i)
    )


#: The controller at one ``(t, y)``, compiled as one program: `quadrotor` and
#: `Quadrotor.for_step` sample it outside any ``jit``, where op by op a first call would
#: compile each operation on its own.
_sample_control = eqx.filter_jit(_control_of)


class Quadrotor(Scene):
    """A quadrotor under Lee's controller on ``SO(3) x R^9``, continuous or sampled.

    State: ``y.R = R[None]``; ``y.x = [Omega, x, v]`` (continuous control) or
    ``[Omega, x, v, f, M, c]`` (sampled: the held thrust and moment and the
    number of steps since the last sample), followed by the four rotor thrusts
    ``[f1, f2, f3, f4]`` when the rotors have a time constant, and by the position and
    attitude integrals ``[e_i, e_I]`` when the gains have integral action
    (`QuadrotorGains`). `observe` saves ``R``,
    ``Omega``, ``M`` (the moment applied) and, in `Trajectory.extras`, ``x``, ``v``,
    ``f`` (the thrust applied), ``Rc``, ``Omega_c``, ``dOmega_c``, ``x_d``, ``e_x``,
    ``e_v``, ``e_R``, ``e_Omega`` and ``Psi`` (the controller's view of the saved
    state, with its continuous-time formulas); with rotors also ``rotor_thrust``
    (the four thrusts produced, `(4,)`) and ``f_cmd``, ``M_cmd`` (the controller's
    command; ``f`` and ``M`` are then ``A`` times the rotor thrusts); with integral
    action also ``e_i`` and ``e_I`` (the integrals, `(3,)` each).

    The integrals of continuous control are integrated with the rest of ``y.x``
    (``e_i' = e_v + c1 e_x``, ``e_I' = e_Omega + c2 e_R``; an integral at its clamp
    ``sigma`` stops growing outward: conditional integration, so it overshoots the
    clamp by one step at most, and the controller reads ``sat(e)``). Under sampled
    control the controller integrates at its samples (zero derivative between them):
    at ``t_k = k T``, ``k >= 1``, ``e_i <- clip(e_i + T (e_v + c1 e_x), -sigma_i,
    sigma_i)``, then the control is computed with the new ``e_i``, then ``e_I <-
    clip(e_I + T (e_Omega + c2 e_R), -sigma_I, sigma_I)`` from its errors and ``M``
    takes the new ``e_I`` (the rectangle rule at the samples, the FDCL's clamp of the
    integral state); both start at 0, and the sample at ``t = 0`` does not add.

    The rotor lag is integrated with the rest of ``y.x`` by the run's Lie-group
    method (a vector-space part of the state, like ``v``); with sampled control its
    input is constant over each hold.

    **Fields:**

    - `vehicle`: a `QuadrotorVehicle`.
    - `gains`: a `QuadrotorGains`.
    - `reference`: a function ``t -> (x_d(t), b1_d(t))``.
    - `y0`: the initial `LieState`.
    - `control_period`: ``T`` (an array) or ``None`` (continuous control).
    - `steps_per_sample`: ``T / dt``, set by `for_step` (``None`` before).

    ``rotors``, ``drag``, ``wind`` and ``noise`` are ``None`` here (class attributes:
    the vehicle is the controller's nominal model, its sensors exact); `quadrotor` given any of them
    builds a `QuadrotorPlant`, which carries them as fields.
    """

    vehicle: QuadrotorVehicle
    gains: QuadrotorGains
    reference: Callable
    y0: LieState
    control_period: Array | None = None
    steps_per_sample: Array | None = None
    rotors: ClassVar[Rotors | None] = None
    drag: ClassVar[Array | None] = None
    wind: ClassVar[Array | Callable | None] = None
    noise: ClassVar[SensorNoise | None] = None

    @property
    def sampled(self) -> bool:
        return self.control_period is not None

    @property
    def lagged(self) -> bool:
        """Whether the rotor thrusts are state (rotors with a time constant)."""
        return self.rotors is not None and self.rotors.lagged

    @property
    def _rotor_slots(self) -> slice:
        start = _COUNTER + 1 if self.sampled else _N
        return slice(start, start + _N_ROTORS)

    @property
    def integral(self) -> bool:
        """Whether the controller has integral action (``gains.integral``): the
        integrals ``[e_i, e_I]`` are then the last six entries of ``y.x``."""
        return self.gains.integral

    @property
    def _integral_slots(self) -> slice:
        start = self._rotor_slots.stop if self.lagged else self._rotor_slots.start
        return slice(start, start + 6)

    def _check_state(self) -> None:
        """``ValueError`` where the state has no slots for the gains' integrals (or slots
        for integrals the gains do not have): gains swapped into a scene built without."""
        n = self._integral_slots.stop if self.integral else self._integral_slots.start
        if self.y0.x.shape[-1] != n:
            want = "with" if self.integral else "without"
            raise ValueError(
                f"the gains are {want} integral action (k_i, k_I) but the scene's state is "
                f"not: build the scene {want} them, scenes.quadrotor(..., gains=...), "
                "instead of swapping the gains in"
            )

    def with_inertia(self, body):
        """The vehicle with another body (the control held at ``t = 0`` is sampled anew)."""
        y0, v = self.y0, self.vehicle
        return quadrotor(
            v.mass,
            body,
            self.gains,
            self.reference,
            x0=y0.x[3:6],
            v0=y0.x[6:9],
            R0=y0.R[0],
            Omega0=y0.x[0:3],
            g=v.g,
            control_period=self.control_period,
            rotors=self.rotors,
            drag=self.drag,
            wind=self.wind,
            noise=self.noise,
        )

    def sweep_hook(self):
        """How `so3jax.sweep` runs this scene: `so3jax._sweep_hooks.QuadrotorSweep`."""
        from ._sweep_hooks import QuadrotorSweep

        return QuadrotorSweep()

    def steps_per_hold(self, dt) -> int:
        """``control_period / dt``; ``ValueError`` unless ``dt`` divides the period.

        Call it eagerly where ``dt`` and the period are known (`simulate` does
        through `for_step`; a traced period inside ``jit`` cannot be checked).
        """
        return _steps_per_hold(self.control_period, dt)

    def control(self, t, y) -> QuadrotorControl:
        """The controller at ``(t, y)`` (continuous-time formulas)."""
        R = y.R[..., 0, :, :]
        Omega, x, v = y.x[..., 0:3], y.x[..., 3:6], y.x[..., 6:9]
        if self.integral:
            e = y.x[..., self._integral_slots]
            return quadrotor_control(
                self.gains, self.vehicle, t, x, v, R, Omega, self.reference, e[..., :3], e[..., 3:]
            )
        return quadrotor_control(self.gains, self.vehicle, t, x, v, R, Omega, self.reference)

    def _integral_rates(self, y, c: QuadrotorControl) -> Array:
        """``[e_i', e_I']`` under continuous control, 0 where an integral at its clamp
        would grow outward (conditional integration)."""
        g = self.gains
        e = y.x[..., self._integral_slots]
        rate = jnp.concatenate([c.e_v + g.c1 * c.e_x, c.e_Omega + g.c2 * c.e_R], -1)
        shape = e.shape[:-1] + (3,)
        sigma = jnp.concatenate(
            [jnp.broadcast_to(g.sigma_i, shape), jnp.broadcast_to(g.sigma_I, shape)], -1
        )
        return jnp.where((jnp.abs(e) >= sigma) & (e * rate > 0), 0.0, rate)

    def measured(self, t, y) -> LieState:
        """The state the controller reads at a sample at ``t``: ``y`` itself without
        `noise`, else ``y`` with the attitude, rate, position and velocity perturbed
        (`SensorNoise.perturb`, at the sample ``round(t / control_period)``)."""
        if self.noise is None:
            return y
        R, Omega, x, v = self.noise.perturb(
            t, self.control_period, y.R[..., 0, :, :], y.x[..., 0:3], y.x[..., 3:6], y.x[..., 6:9]
        )
        return LieState(R[..., None, :, :], jnp.concatenate([Omega, x, v, y.x[..., _N:]], -1))

    def fault(self, t, y):
        """`COMMAND_UNDEFINED` where the commanded attitude at ``(t, y)`` is undefined.

        ``Rc`` needs a thrust direction ``b3c`` and a heading ``b1_d`` not parallel
        to it; where either fails, `_commanded_attitude` gives NaN.
        """
        Rc = self.control(t, y).Rc
        return jnp.where(jnp.isnan(Rc).any((-2, -1)), COMMAND_UNDEFINED, OK)

    def commanded(self, t, y) -> tuple[Array, Array]:
        """``(f, M)`` the controller commands at ``(t, y)``: held, or evaluated now."""
        if self.sampled:
            return y.x[..., 9], y.x[..., 10:13]
        c = self.control(t, y)
        return c.f, c.M

    def rotor_thrusts(self, y, f_cmd, M_cmd) -> tuple[Array, Array]:
        """``(thrusts, commands)`` of the four rotors, shape `(..., 4)` each.

        The commands are ``A^-1 [f_cmd, M_cmd]`` clipped (`Rotors.command`); the
        thrusts are the lagged state, or the commands themselves without a lag.
        """
        cmd = self.rotors.command(f_cmd, M_cmd)
        return (y.x[..., self._rotor_slots] if self.lagged else cmd), cmd

    def drag_force(self, t, y) -> Array:
        """The drag force ``-R diag(d) R^T (v - w(t))`` in N, world frame, shape `(..., 3)`."""
        R, v = y.R[..., 0, :, :], y.x[..., 6:9]
        if self.wind is not None:
            v = v - (self.wind(t) if callable(self.wind) else self.wind)
        return -_mv(R, self.drag * _mv(_mT(R), v))

    def vector_field(self, t, y):
        R = y.R[..., 0, :, :]
        Omega, v = y.x[..., 0:3], y.x[..., 6:9]
        if self.integral and not self.sampled:
            c = self.control(t, y)
            f, M = c.f, c.M
        else:
            f, M = self.commanded(t, y)
        if self.rotors is not None:
            thrusts, cmd = self.rotor_thrusts(y, f, M)
            f, M = self.rotors.wrench(thrusts)
        e3 = _e3(y.x.dtype)
        dOmega = self.vehicle.body.euler_rhs(Omega, M)
        dv = self.vehicle.g * e3 - (f / self.vehicle.mass)[..., None] * _mv(R, e3)
        if self.drag is not None:
            dv = dv + self.drag_force(t, y) / self.vehicle.mass
        parts = [dOmega, v, dv]
        if self.sampled:
            parts.append(jnp.zeros_like(y.x[..., _N : _COUNTER + 1]))
        if self.lagged:
            parts.append(self.rotors.lag_rate(thrusts, cmd))
        if self.integral:
            e = y.x[..., self._integral_slots]
            parts.append(jnp.zeros_like(e) if self.sampled else self._integral_rates(y, c))
        return LieTangent(Omega[..., None, :], jnp.concatenate(parts, -1))

    def for_step(self, dt, t0):
        """Record ``T / dt`` (``dt`` must divide ``T``) and sample the controller at ``t0``.

        A state whose step counter is 0 sits at a sample time: its held
        ``(f, M)`` are recomputed from ``(t0, y0)``, so a scene whose gains were
        swapped (`eqx.tree_at`, `tune`) starts from its own first sample, and
        a run restarted at a sample boundary continues exactly. A restart
        inside a hold (counter > 0) keeps the held values.

        Lagged rotor thrusts start, in a run from ``t0 = 0``, at the clipped
        command at ``(0, y0)`` (recomputed like the held control); a run from
        ``t0 != 0`` continues from the thrusts in ``y0``.
        """
        self._check_state()
        if not self.sampled:
            return _start_rotors(self, t0) if self.lagged else self
        T = self.control_period
        if _is_concrete(dt) and _is_concrete(T):
            n = jnp.asarray(self.steps_per_hold(dt), T.dtype)
        else:
            n = jnp.maximum(jnp.round(T / dt), 1.0).astype(T.dtype)
        scene = eqx.tree_at(lambda s: s.steps_per_sample, self, n, is_leaf=lambda a: a is None)
        y = self.y0
        c = _sample_control(self, jnp.asarray(t0, y.x.dtype), y)
        at_sample = (y.x[..., _COUNTER] == 0)[..., None]
        held = jnp.where(at_sample, jnp.concatenate([c.f[..., None], c.M], -1), y.x[..., _HELD])
        x = jnp.concatenate([y.x[..., :_N], held, y.x[..., _COUNTER:]], -1)
        scene = eqx.tree_at(lambda s: s.y0, scene, LieState(y.R, x))
        return _start_rotors(scene, t0) if self.lagged else scene

    def jump(self, t, y):
        if not self.sampled:
            return y
        if self.steps_per_sample is None:
            raise ValueError(
                "a sampled-data quadrotor (control_period given) runs with fixed steps that "
                "divide control_period: simulate(scene, method, dt, n_steps); adaptive steps "
                "do not apply"
            )
        count = y.x[..., _COUNTER] + 1.0
        sample = count > self.steps_per_sample - 0.5
        if self.integral:
            return self._jump_integral(t, y, count, sample)
        c = _control_of(self, t, y)
        new = jnp.concatenate([c.f[..., None], c.M], -1)
        held = jnp.where(sample[..., None], new, y.x[..., _HELD])
        count = jnp.where(sample, jnp.zeros_like(count), count)
        parts = [y.x[..., :_N], held, count[..., None]]
        if self.lagged:
            parts.append(y.x[..., self._rotor_slots])
        return LieState(y.R, jnp.concatenate(parts, -1))

    def _jump_integral(self, t, y, count, sample):
        """`jump` of a sampled controller with integral action: at a sample, the
        integrals take one step of the rectangle rule, clamped, and the held control is
        computed with them (see the class docstring)."""
        g, T = self.gains, self.control_period
        ym = self.measured(t, y)
        e = y.x[..., self._integral_slots]
        x_d, x_d1 = _time_derivatives(lambda s: self.reference(s)[0], jnp.asarray(t, y.x.dtype), 1)
        rate_i = (ym.x[..., 6:9] - x_d1) + g.c1 * (ym.x[..., 3:6] - x_d)
        e_i = jnp.clip(e[..., :3] + T * rate_i, -g.sigma_i, g.sigma_i)
        c = _control_with_position_integral(self, t, ym, e_i)
        e_I = jnp.clip(e[..., 3:] + T * (c.e_Omega + g.c2 * c.e_R), -g.sigma_I, g.sigma_I)
        new = jnp.concatenate([c.f[..., None], c.M - g.k_I * e_I], -1)
        held = jnp.where(sample[..., None], new, y.x[..., _HELD])
        e = jnp.where(sample[..., None], jnp.concatenate([e_i, e_I], -1), e)
        count = jnp.where(sample, jnp.zeros_like(count), count)
        parts = [y.x[..., :_N], held, count[..., None]]
        if self.lagged:
            parts.append(y.x[..., self._rotor_slots])
        return LieState(y.R, jnp.concatenate(parts + [e], -1))

    def observe(self, t, y):
        c = self.control(t, y)
        f, M = (y.x[..., 9], y.x[..., 10:13]) if self.sampled else (c.f, c.M)
        extras = self._observe_rotors(y, f, M) | self._observe_integrals(y)
        return {
            "R": y.R[..., 0, :, :],
            "Omega": y.x[..., 0:3],
            "M": M,
            "x": y.x[..., 3:6],
            "v": y.x[..., 6:9],
            "f": f,
            "Rc": c.Rc,
            "Omega_c": c.Omega_c,
            "dOmega_c": c.dOmega_c,
            "x_d": c.x_d,
            "e_x": c.e_x,
            "e_v": c.e_v,
            "e_R": c.e_R,
            "e_Omega": c.e_Omega,
            "Psi": c.Psi,
        } | extras

    def _observe_integrals(self, y) -> dict[str, Array]:
        if not self.integral:
            return {}
        e = y.x[..., self._integral_slots]
        return {"e_i": e[..., :3], "e_I": e[..., 3:]}

    def _observe_rotors(self, y, f_cmd, M_cmd) -> dict[str, Array]:
        if self.rotors is None:
            return {}
        thrusts, _ = self.rotor_thrusts(y, f_cmd, M_cmd)
        f, M = self.rotors.wrench(thrusts)
        return {"f": f, "M": M, "f_cmd": f_cmd, "M_cmd": M_cmd, "rotor_thrust": thrusts}


class QuadrotorPlant(Quadrotor):
    """A `Quadrotor` whose vehicle is more than the controller's model.

    **Fields:** those of `Quadrotor`, and

    - `rotors`: a `Rotors`, or ``None`` (the commanded ``(f, M)`` is applied).
    - `drag`: ``d``, shape `(3,)`, in N s/m, or ``None`` (no drag).
    - `wind`: ``w``, shape `(3,)` in m/s, or a function ``t -> w(t)``; or ``None``.

    Built by `quadrotor` when any of them is given, so that a nominal scene keeps
    the pytree (and the compiled program) of a plain `Quadrotor`.
    """

    rotors: Rotors | None = None
    drag: Array | None = None
    wind: Array | Callable | None = None


class NoisyQuadrotor(QuadrotorPlant):
    """A `QuadrotorPlant` whose sampled controller reads a noisy state.

    **Fields:** those of `QuadrotorPlant`, and

    - `noise`: a `SensorNoise`, drawn at each sample (`Quadrotor.measured`).

    Built by `quadrotor` when `noise` is given (a scene without noise keeps its pytree).
    """

    noise: SensorNoise | None = None

    def for_step(self, dt, t0):
        """`for_step` of the scene without noise's, with the noise's key as raw words
        (`SensorNoise.unwrapped`): the step draws by integer arithmetic alone."""
        scene = super().for_step(dt, t0)
        return eqx.tree_at(lambda s: s.noise, scene, scene.noise.unwrapped())


def _vector_arg(value, name: str, dtype) -> Array:
    a = _as_float(value)
    if a.shape not in ((), (3,)):
        raise ValueError(
            f"{name} must be a 3-vector (or a scalar for all three), got shape {a.shape}"
        )
    if not _is_concrete(a):
        return jnp.broadcast_to(a, (3,)).astype(dtype)
    an = np.asarray(a)  # NumPy: an eager JAX broadcast and cast compile on first use
    if not np.all(np.isfinite(an)):
        raise ValueError(f"{name} contains NaN or inf")
    return _to_dtype(np.broadcast_to(an, (3,)), dtype)


def quadrotor(
    mass: ArrayLike,
    inertia: ArrayLike | RigidBody,
    gains: QuadrotorGains,
    reference: Callable,
    x0: ArrayLike = 0.0,
    v0: ArrayLike = 0.0,
    R0: ArrayLike | None = None,
    Omega0: ArrayLike = 0.0,
    g: ArrayLike = 9.81,
    control_period: ArrayLike | None = None,
    rotors: Rotors | None = None,
    drag: ArrayLike | None = None,
    wind: ArrayLike | Callable | None = None,
    noise: SensorNoise | None = None,
) -> Quadrotor:
    """A quadrotor tracking a position and heading under Lee's controller on SE(3).

    ``x' = v``, ``m v' = m g e3 - f R e3``, ``R' = R hat(Omega)``,
    ``J Omega' + Omega x J Omega = M`` (``e3`` down, thrust along ``-R e3``),
    with ``(f, M)`` from `quadrotor_control`: evaluated inside the vector field
    (``control_period=None``), or sampled at ``t = k T`` from the state at that
    time and held until the next sample (``control_period=T``: zero-order hold;
    `simulate` then needs a ``dt`` that divides ``T``, and the initial state
    holds the control sampled at ``t = 0``).

    With `rotors`, the commanded ``(f_cmd, M_cmd)`` is allocated to the four
    rotors within their bounds (`Rotors.allocation`: plain clipping, or yaw given up
    first), optionally lagged (``tau f_i' = f_i,cmd - f_i``, the thrusts
    starting at the clipped command at ``t = 0``), and ``(f, M) = A [f1..f4]``
    (Lee et al.'s eq. (1); see `Rotors`) is applied. With `drag`, ``m v'`` gains
    ``-R diag(d) R^T (v - w(t))`` (air at the wind velocity ``w``, world frame).
    The controller is not told: it keeps its nominal model (no limits, lag, drag
    or wind) and computes ``Omega_c``, ``dOmega_c`` from its own command.

    With integral gains (`QuadrotorGains` with ``k_i`` or ``k_I`` nonzero: the
    geometric PID controller of Goodarzi, Lee & Lee, ECC 2013) the state also carries
    the position and attitude integrals ``[e_i, e_I]``, starting at zero: integrated
    with the state under continuous control, summed at the samples under
    `control_period` (see `Quadrotor`), clamped to ``[-sigma, sigma]`` either way.
    They remove the steady position error that a constant unmodelled force (the
    drag in a steady wind) leaves; without them (the default) the scene is the PD
    scene, the same program.

    **Arguments:**

    - `mass`: ``m`` in kg (> 0).
    - `inertia`: `(3, 3)` inertia, 3 principal moments, or a `RigidBody`.
    - `gains`: a `QuadrotorGains` (with integral gains: integral action, decided
      here; swapping integral gains into a scene built without them, or back, is a
      ``ValueError`` when it runs).
    - `reference`: a function ``t -> (x_d(t), b1_d(t))``, both shape `(3,)`,
      differentiable in ``t`` (e.g. `CircleReference`, `FlipReference`).
      ``b1_d`` need not be a unit vector but must not be parallel to ``b3c``.
    - `x0`, `v0`: initial position and velocity, shape `(3,)` (or a scalar).
    - `R0`: initial attitude, shape `(3, 3)` (default the identity: level).
    - `Omega0`: initial body rate, shape `(3,)` (or a scalar).
    - `g`: gravitational acceleration (>= 0).
    - `control_period`: ``T`` in s (> 0) for sampled-and-held control, or ``None``.
    - `rotors`: a `Rotors` (``4 thrust_max >= m g``: the vehicle must be able to
      hover), or ``None`` (the command is applied as it is).
    - `drag`: ``d``, the drag coefficients along the body axes, in N s/m (>= 0),
      shape `(3,)` (or a scalar for all three), or ``None`` (no drag).
    - `wind`: ``w``, the wind velocity in m/s in the world frame: shape `(3,)`,
      or a function ``t -> w(t)`` of shape `(3,)`; ``None`` is still air. It
      acts through the drag (`drag` required). A `Gust` is such a function.
    - `noise`: a `SensorNoise`: at each sample the controller reads the state with
      its attitude, rate, position and velocity perturbed (`Quadrotor.measured`);
      the plant and the saved state are not. Needs `control_period`. ``None``: the
      controller reads the true state.

    The dtype of the scene is that of ``R0`` (default: JAX's default float).

    **Returns:** a `Quadrotor` scene for `simulate`.

    References: T. Lee, M. Leok, N. H. McClamroch, "Geometric tracking control
    of a quadrotor UAV on SE(3)", CDC 2010; F. Goodarzi, D. Lee, T. Lee, "Geometric
    nonlinear PID control of a quadrotor UAV on SE(3)", ECC 2013 (integral action).
    """
    if R0 is None:
        R0 = np.eye(3, dtype=jnp.result_type(float))
    R0 = check_rotation(R0, "R0")
    dtype = R0.dtype
    m = _to_dtype(_check_scalar(mass, "mass", positive=True), dtype)
    g = _to_dtype(_check_scalar(g, "g", positive=False), dtype)
    body = _as_body(inertia, dtype)
    if not isinstance(gains, QuadrotorGains):
        raise TypeError(f"gains must be a QuadrotorGains, got {type(gains).__name__}")
    gains = _cast_floats(gains, dtype)
    _check_reference(reference, dtype, ("x_d", "b1_d"), "so3jax.CircleReference()")
    reference = _cast_floats(reference, dtype)
    x0 = _vector_arg(x0, "x0", dtype)
    v0 = _vector_arg(v0, "v0", dtype)
    Omega0 = _vector_arg(Omega0, "Omega0", dtype)
    T = None
    if control_period is not None:
        T = _to_dtype(_check_scalar(control_period, "control_period", positive=True), dtype)
    vehicle = QuadrotorVehicle(mass=m, body=body, g=g)
    y0 = _quadrotor_state(R0, Omega0, x0, v0)
    plant = _plant_options(rotors, drag, wind, m, g, dtype)
    cls = QuadrotorPlant if plant else Quadrotor
    noise = check_noise(noise, T, dtype)
    if noise is not None:
        plant["noise"], cls = noise, NoisyQuadrotor
    scene = cls(vehicle=vehicle, gains=gains, reference=reference, y0=y0, control_period=T, **plant)
    if scene.integral:
        return eqx.tree_at(lambda s: s.y0, scene, _start_with_integrals(scene))
    if T is not None:
        scene = eqx.tree_at(lambda s: s.y0, scene, _hold_initial_control(scene))
    if scene.lagged:
        scene = eqx.tree_at(lambda s: s.y0, scene, _add_rotor_state(scene))
    return scene


def _plant_options(rotors, drag, wind, m, g, dtype) -> dict:
    """`quadrotor`'s ``rotors``, ``drag`` and ``wind``, checked and cast to ``dtype``."""
    out = {}
    if rotors is not None:
        if not isinstance(rotors, Rotors):
            raise TypeError(f"rotors must be a so3jax.Rotors, got {type(rotors).__name__}")
        rotors.check_hover(m, g)
        out["rotors"] = _cast_floats(rotors, dtype)
    if drag is not None:
        d = _vector_arg(drag, "drag", dtype)
        if _is_concrete(d) and np.any(np.asarray(d) < 0):
            raise ValueError(f"drag must be >= 0 (N s/m), got {np.asarray(d)}")
        out["drag"] = d
    if wind is not None:
        if drag is None:
            raise ValueError("wind acts through the drag: pass drag (N s/m) with wind")
        if callable(wind):
            try:
                shape = jax.eval_shape(wind, jax.ShapeDtypeStruct((), dtype)).shape
            except Exception as e:
                raise ValueError(f"wind(t) failed on a scalar time: {e}") from e
            if shape != (3,):
                raise ValueError(f"wind(t) must return shape (3,), got {shape}")
            out["wind"] = _cast_floats(wind, dtype)
        else:
            out["wind"] = _vector_arg(wind, "wind", dtype)
    return out


@jax.jit
def _quadrotor_state(R0, Omega0, x0, v0) -> LieState:
    return LieState(R0[None], jnp.concatenate([Omega0, x0, v0]))


@eqx.filter_jit
def _add_rotor_state(scene: Quadrotor) -> LieState:
    """The initial state with the rotor thrusts appended: the clipped command at ``t = 0``."""
    y = scene.y0
    f, M = scene.commanded(jnp.zeros((), y.x.dtype), y)
    return LieState(y.R, jnp.concatenate([y.x, scene.rotors.command(f, M)], -1))


@eqx.filter_jit
def _start_rotors(scene: Quadrotor, t0) -> Quadrotor:
    """The scene whose lagged rotor thrusts are set, where ``t0 == 0``, to the clipped
    command at ``(t0, y0)`` (one compiled call; inlined under a trace)."""
    y = scene.y0
    f, M = scene.commanded(jnp.asarray(t0, y.x.dtype), y)
    slots = scene._rotor_slots
    start = jnp.where(t0 == 0, scene.rotors.command(f, M), y.x[..., slots])
    return eqx.tree_at(lambda s: s.y0, scene, LieState(y.R, y.x.at[..., slots].set(start)))


@eqx.filter_jit
def _start_with_integrals(scene: Quadrotor) -> LieState:
    """The initial state of a scene with integral action: ``[Omega, x, v]`` followed by
    the control held at ``t = 0`` (sampled), the rotor thrusts at the clipped command
    at ``t = 0`` (lagged) and the integrals, zero (one compiled call)."""
    y = scene.y0
    n = scene._integral_slots.stop
    y = LieState(y.R, jnp.concatenate([y.x, jnp.zeros(n - y.x.shape[-1], y.x.dtype)]))
    t0 = jnp.zeros((), y.x.dtype)
    if scene.sampled:
        c = _control_of(scene, t0, y)
        y = LieState(y.R, y.x.at[_HELD].set(jnp.concatenate([c.f[None], c.M])))
    if scene.lagged:
        f, M = scene.commanded(t0, y)
        y = LieState(y.R, y.x.at[scene._rotor_slots].set(scene.rotors.command(f, M)))
    return y


@eqx.filter_jit
def _hold_initial_control(scene: Quadrotor) -> LieState:
    """The initial state with the control sampled at ``t = 0`` held (one compiled call)."""
    y0 = scene.y0
    c = _control_of(scene, jnp.zeros((), y0.x.dtype), y0)
    held = jnp.concatenate([c.f[None], c.M, jnp.zeros(1, y0.x.dtype)])
    return LieState(y0.R, jnp.concatenate([y0.x, held]))


# --------------------------------------------------------------------------
# Ready scenes
# --------------------------------------------------------------------------


def _float_dtype(dtype):
    return jnp.result_type(float) if dtype is None else jnp.dtype(dtype)


def _difftune_vehicle_gains(dtype):
    # NumPy constants: eager JAX ones compile a program each on first use.
    k_x, k_v, k_R, k_O = (np.full(3, k, dtype) for k in DIFFTUNE_GAINS)
    return np.asarray(DIFFTUNE_INERTIA, dtype), QuadrotorGains(k_x, k_v, k_R, k_O)


def quadrotor_circle(
    control_period=0.0025, gains: QuadrotorGains | None = None, dtype=None
) -> Quadrotor:
    """DiffTune's quadrotor example: a circle of radius 2 m at 1 rad/s, sampled control.

    ``m = 4.34`` kg, ``J = diag(0.0820, 0.0845, 0.1377)`` kg m^2, gains
    ``k_x = 16``, ``k_v = 5.6``, ``k_R = 8.81``, ``k_Omega = 2.54`` on every axis
    (3-vectors: 12 tunable numbers), ``x_d = (2 (1 - cos t), 2 sin t, 0.1 sin t)``,
    ``b1_d = e1``, start at rest at the origin, level, with
    ``Omega0 = (0, 0, 0.001)``; control held over ``control_period`` (0.0025 s).
    DiffTune runs it for 10 s.

    **Arguments:**

    - `control_period`: ``T`` in s, or ``None`` for continuous control.
    - `gains`: other `QuadrotorGains` (default: those above).
    - `dtype`: float dtype.

    References: S. Cheng, M. Kim, L. Song, C. Yang, Y. Jin, S. Wang, N. Hovakimyan,
    "DiffTune: Auto-Tuning through Auto-Differentiation", IEEE T-RO 2024.
    """
    dtype = _float_dtype(dtype)
    J, g0 = _difftune_vehicle_gains(dtype)
    return quadrotor(
        np.asarray(DIFFTUNE_MASS, dtype),
        J,
        g0 if gains is None else gains,
        CircleReference(2.0, 1.0, 0.1),
        R0=np.eye(3, dtype=dtype),
        Omega0=np.asarray([0.0, 0.0, 0.001], dtype),
        control_period=control_period,
    )


def quadrotor_recovery(
    control_period=None, dtype=None, *, gains: QuadrotorGains | None = None
) -> Quadrotor:
    """The paper's recovery: hover at the origin from a nearly upside-down start.

    The second case of the numerical example of Lee, Leok & McClamroch (CDC
    2010): their vehicle (``m = 4.34`` kg, ``J = diag(0.0820, 0.0845, 0.1377)``
    kg m^2) and their gains ``k_x = 16 m = 69.44``, ``k_v = 5.6 m = 24.304``,
    ``k_R = 8.81``, ``k_Omega = 2.54`` on every axis (DiffTune's ``k_x = 16``,
    ``k_v = 5.6`` are those of `quadrotor_circle`), at rest at the origin with
    ``R0 = [[1, 0, 0], [0, -0.9995, -0.0314], [0, 0.0314, -0.9995]]``,
    ``x_d = 0`` and ``b1_d = e1``. The paper's matrix is not exactly orthogonal
    (``0.9995^2 + 0.0314^2 = 1 - 1.4e-5``); we take its nearest rotation,
    ``178.2`` degrees about ``e1``, where
    ``Psi(R0, I) = 1 + 0.9995 / sqrt(0.9995^2 + 0.0314^2) = 1.99951``.

    **Arguments:**

    - `control_period`: ``T`` in s for sampled-and-held control, or ``None``
      (continuous control, as in the paper).
    - `dtype`: float dtype.
    - `gains`: other `QuadrotorGains` (default: the paper's, on every axis).

    **Returns:** a `Quadrotor` scene.

    References: T. Lee, M. Leok, N. H. McClamroch, "Geometric tracking control
    of a quadrotor UAV on SE(3)", CDC 2010 (numerical example, the case
    starting upside down).
    """
    from ._so3 import project

    dtype = _float_dtype(dtype)
    J = np.asarray(DIFFTUNE_INERTIA, dtype)
    if gains is None:
        gains = QuadrotorGains(*(np.full(3, k, dtype) for k in PAPER_GAINS))
    R0 = project(np.asarray(RECOVERY_R0, dtype))
    return quadrotor(
        np.asarray(DIFFTUNE_MASS, dtype),
        J,
        gains,
        HoverReference(np.zeros(3, dtype)),
        R0=R0,
        control_period=control_period,
    )


def quadrotor_flip(control_period=None, dtype=None) -> Quadrotor:
    """A flip: hover, one vertical loop of radius 1 m in 3 s from t = 1 s, hover again.

    See `FlipReference`; DiffTune's vehicle and gains, start at rest, level, at
    the origin.
    """
    dtype = _float_dtype(dtype)
    J, gains = _difftune_vehicle_gains(dtype)
    return quadrotor(
        np.asarray(DIFFTUNE_MASS, dtype),
        J,
        gains,
        FlipReference(),
        R0=np.eye(3, dtype=dtype),
        control_period=control_period,
    )


# --------------------------------------------------------------------------
# Sweeps: gains x initial attitudes
# --------------------------------------------------------------------------


def sweep_quadrotor(
    scene: Quadrotor,
    gains: QuadrotorGains,
    R0: ArrayLike,
    *,
    method=None,
    dt: float = 0.0025,
    n_steps: int = 2000,
    save_every: int = 4,
    threshold: float = 0.05,
) -> dict[str, np.ndarray]:
    """Quadrotor runs for every gain set crossed with every initial attitude.

    `so3jax.sweep` is built around the attitude-only tracking scene (its
    statistics are ``Psi(R, Rd)`` and the torque); for the quadrotor this is
    the same idea without its chunking and resuming: one `jax.vmap` of
    `simulate` over the ``G x N`` runs, compiled once, returning a few numbers
    per run. Runs that diverge are flagged by their status and have NaN metrics.

    **Arguments:**

    - `scene`: a `Quadrotor` scene (its vehicle, reference, ``x0``, ``v0``,
      ``Omega0`` and control period are kept; gains and ``R0`` replaced).
    - `gains`: a `QuadrotorGains` whose leaves have a leading axis ``G``, e.g.
      ``jax.vmap(QuadrotorGains)(k_x, k_v, k_R, k_Omega)``.
    - `R0`: initial attitudes, shape `(N, 3, 3)` (upside-down starts welcome:
      ``Psi(R0, I)`` close to 2).
    - `method`: a Lie-group method (default `RKMK4()`).
    - `dt`, `n_steps`, `save_every`: as in `simulate`.
    - `threshold`: settling threshold on ``|e_x|`` in m.

    **Returns:** a dict of NumPy arrays of shape `(G, N)`: ``final_position_error``,
    ``max_position_error``, ``rms_position_error``, ``settling_time`` (first saved
    time after which ``|e_x| < threshold`` for good; ``inf`` if never),
    ``final_psi``, ``min_thrust_axis_up`` (the least ``R_33 = (-R e3) . (-e3)``,
    the cosine between thrust axis and up, over the saved points: below 0 means
    the vehicle was upside down), ``status_code``.
    """
    from ._integrators import RKMK4
    from ._simulate import simulate
    from ._trajectory import OK, settling_time

    if not isinstance(scene, Quadrotor):
        raise TypeError(f"scene must be a Quadrotor scene, got {type(scene).__name__}")
    if not isinstance(gains, QuadrotorGains):
        raise TypeError(f"gains must be a batched QuadrotorGains, got {type(gains).__name__}")
    dtype = scene.y0.R.dtype
    R0 = jnp.asarray(R0, dtype)
    if R0.ndim != 3 or R0.shape[1:] != (3, 3):
        raise ValueError(f"R0 must have shape (N, 3, 3), got {R0.shape}")
    shapes = {jnp.shape(k)[:1] for k in jax.tree.leaves(gains)}
    if len(shapes) != 1 or shapes == {()}:
        raise ValueError("gains must have one leading batch axis G on every field")
    (G,) = shapes.pop()
    N = R0.shape[0]
    gains = _cast_floats(gains, dtype)
    method = RKMK4() if method is None else method
    if scene.sampled:  # inside the jitted batch the period is traced: check it here
        scene.steps_per_hold(dt)

    def one(g, R):
        sc = eqx.tree_at(lambda s: (s.gains, s.y0), scene, (g, _restart(scene, R)))
        tr = simulate(sc, method, dt, n_steps, save_every)
        ok = tr.status.code == OK
        e, out = position_metrics(tr)
        out["settling_time"] = settling_time(tr.t, e < threshold)
        out["final_psi"] = tr.extras["Psi"][-1]
        nan = jnp.array(jnp.nan, dtype)
        out = {k: jnp.where(ok, v, nan) for k, v in out.items()}
        out["status_code"] = tr.status.code
        return out

    gi = jnp.repeat(jnp.arange(G), N)
    ri = jnp.tile(jnp.arange(N), G)
    run = eqx.filter_jit(jax.vmap(one))
    out = run(jax.tree.map(lambda a: a[gi], gains), R0[ri])
    return {k: np.asarray(v).reshape(G, N) for k, v in out.items()}


def position_metrics(tr) -> tuple[Array, dict]:
    """``(|e_x|, metrics)`` of a quadrotor `Trajectory` over its saved points.

    ``metrics``: ``final_position_error``, ``max_position_error``,
    ``rms_position_error`` and ``min_thrust_axis_up``, the least
    ``R_33 = cos(thrust axis, up)`` (``e3`` down, thrust along ``-R e3``;
    below 0: upside down). Failed runs are for the caller to mask.
    """
    e = jnp.sqrt(jnp.sum(tr.extras["e_x"] ** 2, -1))
    return e, {
        "final_position_error": e[-1],
        "max_position_error": jnp.max(e),
        "rms_position_error": jnp.sqrt(jnp.mean(e**2)),
        "min_thrust_axis_up": jnp.min(tr.R[:, 2, 2]),
    }


def _restart(scene: Quadrotor, R0: Array) -> LieState:
    """The initial state of ``scene`` with attitude ``R0``, at a sample time.

    With the step counter at 0, `Quadrotor.for_step` samples the controller
    (with the run's gains) from this state when `simulate` starts.
    """
    x = scene.y0.x
    if scene.sampled:
        x = x.at[_COUNTER].set(0.0)
    return LieState(R0[None], x)
