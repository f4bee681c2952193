"""Sensor noise: the state a sampled controller sees.

At the sample ``k`` (time ``t_k = k T``, ``T`` the control period) the controller
reads, in place of the true state,

    R_seen = R exp(hat(xi_R)),   Omega_seen = Omega + xi_Omega,
    x_seen = x + xi_x,           v_seen = v + xi_v,

with independent Gaussian ``xi ~ N(0, diag(sigma^2))`` per axis: the attitude error
is a Gaussian tangent in the body frame (the "concentrated Gaussian" on SO(3) of
Barfoot & Furgale), the others additive. The draws of sample ``k`` come from
``jax.random.fold_in(key, k)``: a run is reproducible from its key, whatever the
integrator or the number of steps per hold. The plant is not perturbed.

References: T. D. Barfoot, P. T. Furgale, "Associating uncertainty with
three-dimensional poses for use in estimation problems", IEEE T-RO 30(3), 2014.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._repr import module_repr
from ._so3 import _as_float, _exp, _is_concrete, _mm, _to_dtype
from ._types import Array, ArrayLike

_FIELDS = ("attitude", "rate", "position", "velocity")
_UNITS = {"attitude": "rad", "rate": "rad/s", "position": "m", "velocity": "m/s"}


def _std(value, name: str) -> Array:
    a = _as_float(value)
    if a.shape not in ((), (3,)):
        raise ValueError(
            f"SensorNoise.{name} must be a scalar or a 3-vector (a standard deviation in "
            f"{_UNITS[name]} per axis), got shape {a.shape}"
        )
    if _is_concrete(a):
        an = np.asarray(a, np.float64)
        if not (np.all(np.isfinite(an)) and np.all(an >= 0)):
            raise ValueError(
                f"SensorNoise.{name} must be >= 0 and finite (a standard deviation in "
                f"{_UNITS[name]}), got {an}"
            )
    return a


def _as_key(key):
    if isinstance(key, int):
        return jax.random.key(key)
    try:
        jax.random.key_data(key)
    except (TypeError, ValueError):
        raise ValueError(
            f"SensorNoise.key must be a JAX PRNG key or an int seed, got {key!r}"
        ) from None
    return key


class SensorNoise(eqx.Module):
    """Gaussian noise on the state a sampled controller sees.

    At each sample ``k`` the controller reads ``R exp(hat(xi_R))``,
    ``Omega + xi_Omega``, ``x + xi_x``, ``v + xi_v`` instead of the true state, with
    ``xi_* ~ N(0, sigma_*^2)`` independent per axis, drawn from
    ``jax.random.fold_in(key, k)``. Pass it as ``noise=`` to `scenes.quadrotor` or
    `scenes.tracking` (which have no position or velocity: only `attitude` and `rate`
    apply), with a ``control_period``. A zero standard deviation leaves its part of
    the state exactly as it is; a scene given a `SensorNoise` whose standard
    deviations are all zero (concrete values) drops it, and runs bit for bit as
    without noise. (Zeros that are traced, such as a batch of intensities under
    ``vmap``, give the noise-free run to round-off: the program differs.)

    **Arguments:**

    - `attitude`: ``sigma_R`` in rad, the standard deviation of the body-frame tangent
      ``xi_R`` (>= 0), a scalar or shape `(3,)`.
    - `rate`: ``sigma_Omega`` in rad/s (>= 0), a scalar or shape `(3,)`.
    - `position`: ``sigma_x`` in m (>= 0), a scalar or shape `(3,)`.
    - `velocity`: ``sigma_v`` in m/s (>= 0), a scalar or shape `(3,)`.
    - `key`: a JAX PRNG key (`jax.random.key` or `jax.random.PRNGKey`) or an int
      seed. ``jax.vmap`` over keys (e.g. through `eqx.tree_at` on ``scene.noise.key``)
      gives a batch of independent runs.

    Bad shapes, and negative or non-finite values when concrete, raise ``ValueError``
    naming the argument.

    References: T. D. Barfoot, P. T. Furgale, IEEE T-RO 30(3), 2014 (Gaussian
    tangents on SO(3)).
    """

    attitude: Array
    rate: Array
    position: Array
    velocity: Array
    key: Array

    __repr__ = module_repr

    def __init__(
        self,
        attitude: ArrayLike = 0.0,
        rate: ArrayLike = 0.0,
        position: ArrayLike = 0.0,
        velocity: ArrayLike = 0.0,
        *,
        key,
    ):
        self.attitude = _std(attitude, "attitude")
        self.rate = _std(rate, "rate")
        self.position = _std(position, "position")
        self.velocity = _std(velocity, "velocity")
        self.key = _as_key(key)

    def draw(self, t, period, batch: tuple[int, ...], dtype) -> tuple[Array, ...]:
        """``(xi_R, xi_Omega, xi_x, xi_v)`` at the sample nearest ``t``, each ``batch + (3,)``.

        The sample index is ``k = round(t / period)``; the draws are
        ``sigma * N(0, 1)`` from ``jax.random.fold_in(key, k)``.
        """
        k = jnp.round(jnp.asarray(t, dtype) / period).astype(jnp.int32)
        z = jax.random.normal(jax.random.fold_in(self.key, k), (*batch, 4, 3), dtype)
        return tuple(
            jnp.asarray(getattr(self, name), dtype) * z[..., i, :] for i, name in enumerate(_FIELDS)
        )

    def perturb(self, t, period, R, Omega, x=None, v=None) -> tuple[Array, ...]:
        """The state the controller sees at the sample nearest ``t``.

        **Arguments:**

        - `t`: time, shape `()`; `period`: the control period ``T``.
        - `R`: attitude, shape `(..., 3, 3)`; `Omega`: body rate, shape `(..., 3)`.
        - `x`, `v`: position and velocity, shape `(..., 3)`, or ``None`` (attitude
          scenes).

        **Returns:** ``(R exp(hat(xi_R)), Omega + xi_Omega)``, followed by
        ``x + xi_x`` and ``v + xi_v`` when `x` and `v` are given.
        """
        xi_R, xi_W, xi_x, xi_v = self.draw(t, period, Omega.shape[:-1], Omega.dtype)
        out = (_mm(R, _exp(xi_R)), Omega + xi_W)
        if x is not None:
            out = out + (x + xi_x, v + xi_v)
        return out


def _stds(noise, attitude_only: bool) -> list:
    fields = _FIELDS[:2] if attitude_only else _FIELDS
    return [getattr(noise, f) for f in fields]


def check_noise(noise, control_period, dtype, *, attitude_only: bool = False):
    """A scene's ``noise`` argument checked (a `SensorNoise`, with a control period)
    and its standard deviations cast to ``dtype``.

    ``None`` stays ``None``, and so does a `SensorNoise` whose standard deviations
    are all concrete zeros: the scene is then the noise-free one, the same program
    (XLA compiles a program with the draws differently, which moves the run by
    round-off even where the draws are zero).
    """
    if noise is None:
        return None
    if not isinstance(noise, SensorNoise):
        raise TypeError(f"noise must be a so3jax.SensorNoise, got {type(noise).__name__}")
    if control_period is None:
        raise ValueError(
            "noise perturbs the state a sampled controller sees: pass control_period "
            "(sampled-and-held control) with noise"
        )
    if attitude_only:
        for name in ("position", "velocity"):
            a = getattr(noise, name)
            if _is_concrete(a) and np.any(np.asarray(a) != 0):
                raise ValueError(
                    f"noise: an attitude scene has no {name}; SensorNoise.{name} must be 0, "
                    f"got {np.asarray(a)}"
                )
    if all(_is_concrete(a) and not np.any(np.asarray(a)) for a in _stds(noise, attitude_only)):
        return None
    return eqx.tree_at(
        lambda n: tuple(getattr(n, f) for f in _FIELDS),
        noise,
        tuple(_to_dtype(getattr(noise, f), dtype) for f in _FIELDS),
    )
