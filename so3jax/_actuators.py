"""The quadrotor's rotors: allocation, thrust limits and a first-order lag.

Lee, Leok & McClamroch (CDC 2010), eq. (1), place four rotors on the body
axes ``b1`` (rotor 1), ``b2`` (2), ``-b1`` (3), ``-b2`` (4) at a distance ``d``
from the centre; rotors 1 and 3 turn one way, 2 and 4 the other, and a
rotor's reaction torque is ``c`` times its thrust. Thrust and moment follow
from the four thrusts ``f_i`` (each along ``-b3``) as

    [f, M1, M2, M3]^T = A [f1, f2, f3, f4]^T,
    A = [[1, 1, 1, 1], [0, -d, 0, d], [d, 0, -d, 0], [-c, c, -c, c]].

`Rotors` maps a commanded ``(f, M)`` to rotor thrusts by ``A^-1`` (in closed
form), clips each to ``[thrust_min, thrust_max]`` (or, with
``allocation="yaw_last"``, first gives up yaw, then collective thrust, then roll
and pitch), and, with a time constant ``tau``, lets the thrusts follow the command
with a first-order lag ``tau f_i' = f_i,cmd - f_i``. The vehicle then feels
``A [f1, f2, f3, f4]``.

References: T. Lee, M. Leok, N. H. McClamroch, "Geometric tracking control of a
quadrotor UAV on SE(3)", CDC 2010, eq. (1); E. J. J. Smeur, D. C. Hoeppener,
C. De Wagter, "Prioritized control allocation for quadrotors subject to
saturation", IMAV 2017 (the priority order of ``"yaw_last"``).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._repr import module_repr
from ._so3 import _as_float, _is_concrete
from ._types import Array, ArrayLike


def _scalar(value, name: str) -> Array:
    a = _as_float(value)
    if a.shape != ():
        raise ValueError(f"{name} must be a scalar, got shape {a.shape}")
    return a


def _concrete(a: Array) -> float | None:
    return float(np.asarray(a)) if _is_concrete(a) else None


#: The allocation policies of `Rotors`.
ALLOCATIONS = ("clip", "yaw_last")


class Rotors(eqx.Module):
    """Four rotors in the '+' layout of Lee, Leok & McClamroch: allocation, limits, lag.

    ``[f, M] = A [f1, f2, f3, f4]`` with
    ``A = [[1, 1, 1, 1], [0, -d, 0, d], [d, 0, -d, 0], [-c, c, -c, c]]``;
    a commanded ``(f, M)`` becomes four rotor commands ``f_i,cmd`` within
    ``[thrust_min, thrust_max]`` by the `allocation` policy. Without a time
    constant the rotors produce their commands at once; with ``tau`` their thrusts
    are state and follow ``tau f_i' = f_i,cmd - f_i``.

    **Allocation policies** (``lo``, ``hi`` the thrust limits):

    - ``"clip"`` (the default): ``f_i,cmd = clip((A^-1 [f, M])_i, lo, hi)``, rotor
      by rotor. A rotor at its limit takes thrust, roll, pitch and yaw with it
      alike; with a small ``c`` (Lee et al.'s ``c = 8e-4`` m) a modest yaw moment
      alone drives every rotor to a limit.
    - ``"yaw_last"``: roll and pitch first, then the collective thrust, then yaw:
      the priority order Smeur, Hoeppener & De Wagter propose for quadrotors,
      here applied in sequence and in closed form (not by their weighted least
      squares). With ``a = M2 / (2d)``, ``b = M1 / (2d)``, ``y = M3 / (4c)``
      (so that ``A^-1 [f, M] = f/4 + (a - y, -b + y, -a - y, b + y)``):

      1. Roll and pitch: ``m = max(|a|, |b|)``. Where even they do not fit
         (``2 m > hi - lo``), ``a`` and ``b`` are scaled by ``(hi - lo) / (2 m)``
         (the torque direction kept) and ``m`` becomes ``(hi - lo) / 2``.
      2. Collective thrust: ``q = clip(f/4, lo + m, hi - m)``; the thrusts
         ``g = (q + a, q - b, q - a, q + b)``, which give ``(4q, M1, M2, 0)``, are
         within bounds.
      3. Yaw: ``y' = clip(y, -H_-, H_+)`` with the headroom
         ``H_+ = min(g1 - lo, g3 - lo, hi - g2, hi - g4)`` and
         ``H_- = min(hi - g1, hi - g3, g2 - lo, g4 - lo)``. That is ``y' = k y``
         with ``k`` in ``[0, 1]`` the largest fraction of the commanded yaw moment
         that keeps every rotor within bounds with ``f``, ``M1``, ``M2`` held.
      4. ``f_i,cmd = clip(g_i + s_i y', lo, hi)``, ``s = (-1, 1, -1, 1)`` (this
         last clip only removes round-off).

      Where no limit is reached the result is exactly ``A^-1 [f, M]``; where
      roll and pitch fit they are applied exactly. The collective thrust is
      clipped with the yaw moment at zero, and yaw is only reduced toward zero,
      never used to help the thrust. The policy is piecewise linear in
      ``(f, M)``: it runs under `jit` and `vmap`, and its derivatives are finite
      everywhere.

    **Arguments:**

    - `arm`: ``d``, distance from the centre of mass to each rotor's axis, in m
      (> 0), shape `()`.
    - `torque_coefficient`: ``c``, reaction torque per unit thrust, in m (> 0),
      shape `()`.
    - `thrust_min`: least thrust of one rotor, in N (finite), shape `()`.
    - `thrust_max`: greatest thrust of one rotor, in N (> `thrust_min`; ``inf``
      for no upper limit), shape `()`.
    - `time_constant`: ``tau`` in s (> 0) of the first-order lag of each rotor's
      thrust, or ``None`` (thrust follows the command at once).
    - `allocation`: ``"clip"`` (default) or ``"yaw_last"``, see above.

    Bad shapes and an unknown `allocation` raise ``ValueError`` naming the
    argument; so do bad values when they are concrete (under `jit`/`vmap` they are
    not checked).

    References: T. Lee, M. Leok, N. H. McClamroch, "Geometric tracking control
    of a quadrotor UAV on SE(3)", CDC 2010, eq. (1); E. J. J. Smeur,
    D. C. Hoeppener, C. De Wagter, "Prioritized control allocation for quadrotors
    subject to saturation", IMAV 2017 (``"yaw_last"``: roll and pitch, then
    thrust, then yaw).
    """

    arm: Array
    torque_coefficient: Array
    thrust_min: Array
    thrust_max: Array
    time_constant: Array | None
    allocation: str = eqx.field(static=True)

    __repr__ = module_repr

    def __init__(
        self,
        arm: ArrayLike,
        torque_coefficient: ArrayLike,
        thrust_min: ArrayLike = 0.0,
        thrust_max: ArrayLike = math.inf,
        time_constant: ArrayLike | None = None,
        allocation: str = "clip",
    ):
        if not (isinstance(allocation, str) and allocation in ALLOCATIONS):
            raise ValueError(
                f"allocation must be one of {', '.join(map(repr, ALLOCATIONS))}, got {allocation!r}"
            )
        self.allocation = allocation
        self.arm = _scalar(arm, "arm")
        self.torque_coefficient = _scalar(torque_coefficient, "torque_coefficient")
        self.thrust_min = _scalar(thrust_min, "thrust_min")
        self.thrust_max = _scalar(thrust_max, "thrust_max")
        self.time_constant = (
            None if time_constant is None else _scalar(time_constant, "time_constant")
        )
        for name in ("arm", "torque_coefficient", "time_constant"):
            v = getattr(self, name)
            v = None if v is None else _concrete(v)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive and finite, got {v}")
        lo, hi = _concrete(self.thrust_min), _concrete(self.thrust_max)
        if lo is not None and not math.isfinite(lo):
            raise ValueError(f"thrust_min must be finite, got {lo}")
        if hi is not None and (math.isnan(hi) or hi == -math.inf):
            raise ValueError(f"thrust_max must be a number or inf, got {hi}")
        if lo is not None and hi is not None and not lo < hi:
            raise ValueError(f"thrust_min ({lo}) must be less than thrust_max ({hi})")

    @property
    def lagged(self) -> bool:
        """Whether the rotor thrusts are state (a time constant is given)."""
        return self.time_constant is not None

    def matrix(self) -> Array:
        """``A``, shape `(4, 4)`: ``[f, M1, M2, M3] = A [f1, f2, f3, f4]``."""
        d, c = self.arm, self.torque_coefficient
        z, one = jnp.zeros_like(d), jnp.ones_like(d)
        return jnp.stack(
            [
                jnp.stack([one, one, one, one]),
                jnp.stack([z, -d, z, d]),
                jnp.stack([d, z, -d, z]),
                jnp.stack([-c, c, -c, c]),
            ]
        )

    def allocate(self, f: Array, M: Array) -> Array:
        """``A^-1 [f, M]``, the rotor thrusts that give ``(f, M)`` (not clipped).

        In closed form: ``f1 = f/4 + M2/(2d) - M3/(4c)``, ``f2 = f/4 - M1/(2d) + M3/(4c)``,
        ``f3 = f/4 - M2/(2d) - M3/(4c)``, ``f4 = f/4 + M1/(2d) + M3/(4c)``.

        **Arguments:**

        - `f`: total thrust in N, shape `(...)`.
        - `M`: body moment in N m, shape `(..., 3)`.

        **Returns:** the four thrusts in N, shape `(..., 4)`.
        """
        q = 0.25 * f
        m1 = M[..., 0] / (2.0 * self.arm)
        m2 = M[..., 1] / (2.0 * self.arm)
        m3 = M[..., 2] / (4.0 * self.torque_coefficient)
        return jnp.stack([q + m2 - m3, q - m1 + m3, q - m2 - m3, q + m1 + m3], -1)

    def command(self, f: Array, M: Array) -> Array:
        """The rotor commands for ``(f, M)``, within ``[thrust_min, thrust_max]``.

        ``"clip"``: ``A^-1 [f, M]`` clipped rotor by rotor; ``"yaw_last"``: roll and
        pitch, then thrust, then yaw (see `Rotors`).

        **Arguments:**

        - `f`: total thrust in N, shape `(...)`.
        - `M`: body moment in N m, shape `(..., 3)`.

        **Returns:** the four commands in N, shape `(..., 4)`.
        """
        if self.allocation == "yaw_last":
            return self._yaw_last(f, M)
        return jnp.clip(self.allocate(f, M), self.thrust_min, self.thrust_max)

    def _yaw_last(self, f: Array, M: Array) -> Array:
        """The ``"yaw_last"`` policy, steps 1-4 of `Rotors`' docstring."""
        lo, hi = self.thrust_min, self.thrust_max
        a = M[..., 1] / (2.0 * self.arm)
        b = M[..., 0] / (2.0 * self.arm)
        y = M[..., 2] / (4.0 * self.torque_coefficient)
        # 1. roll and pitch, scaled down (direction kept) where even they do not fit
        half = 0.5 * (hi - lo)
        m = jnp.maximum(jnp.abs(a), jnp.abs(b))
        over = m > half  # false where hi is inf; then m > 0 where true
        scale = jnp.where(over, half / jnp.where(over, m, 1.0), 1.0)
        a, b, m = a * scale, b * scale, jnp.minimum(m, half)
        # 2. the collective thrust, clipped so that roll and pitch fit
        q = jnp.clip(0.25 * f, lo + m, hi - m)
        g1, g2, g3, g4 = q + a, q - b, q - a, q + b
        # 3. yaw, clipped to the headroom of every rotor in the direction it moves
        up = jnp.maximum(jnp.minimum(jnp.minimum(g1, g3) - lo, hi - jnp.maximum(g2, g4)), 0.0)
        down = jnp.maximum(jnp.minimum(hi - jnp.maximum(g1, g3), jnp.minimum(g2, g4) - lo), 0.0)
        y = jnp.clip(y, -down, up)
        # 4. thrusts (the clip removes round-off only)
        thrusts = jnp.stack([g1 - y, g2 + y, g3 - y, g4 + y], -1)
        return jnp.clip(thrusts, lo, hi)

    def wrench(self, thrusts: Array) -> tuple[Array, Array]:
        """``(f, M) = A [f1, f2, f3, f4]``: total thrust `(...)` and body moment `(..., 3)`."""
        f1, f2, f3, f4 = (thrusts[..., i] for i in range(4))
        d, c = self.arm, self.torque_coefficient
        M = jnp.stack([d * (f4 - f2), d * (f1 - f3), c * (f2 + f4 - f1 - f3)], -1)
        return f1 + f2 + f3 + f4, M

    def lag_rate(self, thrusts: Array, command: Array) -> Array:
        """``f_i' = (f_i,cmd - f_i) / tau``, shape `(..., 4)` (rotors with a time constant)."""
        return (command - thrusts) / self.time_constant

    def check_hover(self, mass: Array, g: Array) -> None:
        """``ValueError`` when the rotors cannot hold a hover: ``m g > 4 thrust_max``.

        Checked only where the values are concrete.
        """
        m, gv, hi = _concrete(mass), _concrete(g), _concrete(self.thrust_max)
        if m is not None and gv is not None and hi is not None and m * gv > 4.0 * hi:
            raise ValueError(
                f"rotors.thrust_max ({hi:g} N) cannot hover the vehicle: "
                f"m g = {m * gv:g} N > 4 thrust_max = {4.0 * hi:g} N"
            )
