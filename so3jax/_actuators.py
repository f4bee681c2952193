"""The quadrotor's rotors: allocation, thrust limits and a first-order lag.

Lee, Leok & McClamroch (CDC 2010), eq. (1), place four rotors on the body
axes ``b1`` (rotor 1), ``b2`` (2), ``-b1`` (3), ``-b2`` (4) at a distance ``d``
from the centre; rotors 1 and 3 turn one way, 2 and 4 the other, and a
rotor's reaction torque is ``c`` times its thrust. Thrust and moment follow
from the four thrusts ``f_i`` (each along ``-b3``) as

    [f, M1, M2, M3]^T = A [f1, f2, f3, f4]^T,
    A = [[1, 1, 1, 1], [0, -d, 0, d], [d, 0, -d, 0], [-c, c, -c, c]].

`Rotors` maps a commanded ``(f, M)`` to rotor thrusts by ``A^-1`` (in closed
form), clips each to ``[thrust_min, thrust_max]``, and, with a time constant
``tau``, lets the thrusts follow the clipped command with a first-order lag
``tau f_i' = f_i,cmd - f_i``. The vehicle then feels ``A [f1, f2, f3, f4]``.

References: T. Lee, M. Leok, N. H. McClamroch, "Geometric tracking control of a
quadrotor UAV on SE(3)", CDC 2010, eq. (1).
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


class Rotors(eqx.Module):
    """Four rotors in the '+' layout of Lee, Leok & McClamroch: allocation, limits, lag.

    ``[f, M] = A [f1, f2, f3, f4]`` with
    ``A = [[1, 1, 1, 1], [0, -d, 0, d], [d, 0, -d, 0], [-c, c, -c, c]]``;
    a commanded ``(f, M)`` becomes the rotor commands
    ``f_i,cmd = clip((A^-1 [f, M])_i, thrust_min, thrust_max)``. Without a time
    constant the rotors produce their commands at once; with ``tau`` their thrusts
    are state and follow ``tau f_i' = f_i,cmd - f_i``.

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

    Bad shapes raise ``ValueError`` naming the argument; so do bad values when they
    are concrete (under `jit`/`vmap` they are not checked).

    References: T. Lee, M. Leok, N. H. McClamroch, "Geometric tracking control
    of a quadrotor UAV on SE(3)", CDC 2010, eq. (1).
    """

    arm: Array
    torque_coefficient: Array
    thrust_min: Array
    thrust_max: Array
    time_constant: Array | None

    __repr__ = module_repr

    def __init__(
        self,
        arm: ArrayLike,
        torque_coefficient: ArrayLike,
        thrust_min: ArrayLike = 0.0,
        thrust_max: ArrayLike = math.inf,
        time_constant: ArrayLike | None = None,
    ):
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
        """The rotor commands: ``A^-1 [f, M]`` clipped to ``[thrust_min, thrust_max]``.

        **Returns:** shape `(..., 4)`, in N.
        """
        return jnp.clip(self.allocate(f, M), self.thrust_min, self.thrust_max)

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
