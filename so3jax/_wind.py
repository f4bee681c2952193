"""Gusts: a random wind velocity, one Ornstein–Uhlenbeck process per world axis.

Each component ``w_i(t)`` of the wind (world frame, m/s) is a stationary
Ornstein–Uhlenbeck (first-order Gauss–Markov) process with mean ``mu_i``,
standard deviation ``sigma_i`` and correlation time ``T_i``:

    dw = -(w - mu) / T dt + sigma sqrt(2 / T) dW,
    E[w(t)] = mu,   Cov[w(t), w(t + s)] = sigma^2 exp(-|s| / T).

Its spectrum ``Phi(omega) = sigma^2 (2 T) / (1 + (T omega)^2)`` is Dryden's
longitudinal gust spectrum of MIL-F-8785C with the scale length ``L`` flown at the
airspeed ``V``: ``T = L / V``. (Dryden's lateral and vertical spectra are of second
order; here every axis has the first-order form.)

The path is drawn once, when the `Gust` is built, on the grid ``t_k = k h``
(``k = 0 .. n``) by the exact discretisation of the process (Gillespie 1996):

    z_0 ~ N(0, 1),   z_{k+1} = a z_k + sqrt(1 - a^2) xi_k,   a = exp(-h / T),

a standardised path (mean 0, variance 1 at every grid point, for any ``h``), and
``w(t) = mu + sigma z(t)`` with ``z`` interpolated linearly between grid points.
The wind is then a plain piecewise-linear function of ``t``: deterministic given
the key, the same for every integrator and step, and differentiable in ``t``,
``mu`` and ``sigma``.

References: U.S. Department of Defense, MIL-F-8785C, "Flying Qualities of Piloted
Airplanes", 1980, sec. 3.7 (the Dryden model); D. T. Gillespie, "Exact numerical
simulation of the Ornstein-Uhlenbeck process and its integral", Phys. Rev. E 54,
2084 (1996).
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._repr import module_repr
from ._types import Array, ArrayLike

#: Default grid steps per (shortest) correlation time. Linear interpolation lowers the
#: variance between grid points by at most ``(1 - a) / 2 ~ h / (2 T)``: 2.5 % here.
_STEPS_PER_CORRELATION_TIME = 20


def _per_axis(value, name: str, least: float | None, strict: bool = False) -> np.ndarray:
    """``value`` as a float64 3-vector (a scalar applies to every axis), finite and
    ``>= least`` (``> least`` if `strict`; no bound if ``least`` is ``None``)."""
    try:
        a = np.asarray(value, np.float64)
    except (TypeError, jax.errors.TracerArrayConversionError) as e:
        raise ValueError(f"{name} must be a concrete scalar or 3-vector: {e}") from None
    if a.shape == ():
        a = np.full(3, float(a))
    if a.shape != (3,):
        raise ValueError(f"{name} must be a scalar or a 3-vector (one per axis), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a}")
    if least is not None and not np.all(a > least if strict else a >= least):
        raise ValueError(f"{name} must be {'>' if strict else '>='} {least:g}, got {a}")
    return a


@functools.partial(jax.jit, static_argnums=(2, 3))
def _ou_path(key, a: Array, n: int, dtype) -> Array:
    """``n + 1`` points of a standardised OU path per axis: ``z_{k+1} = a z_k + sqrt(1-a^2) xi``.

    ``z_0`` is drawn from the stationary law ``N(0, 1)``; shape `(n + 1, 3)`.
    """
    k0, k1 = jax.random.split(key)
    z0 = jax.random.normal(k0, (3,), dtype)
    xi = jax.random.normal(k1, (n, 3), dtype)
    b = jnp.sqrt(1.0 - a * a)

    def step(z, x):
        z = a * z + b * x
        return z, z

    _, zs = jax.lax.scan(step, z0, xi)
    return jnp.concatenate([z0[None], zs], 0)


class Gust(eqx.Module):
    """A gusting wind in the world frame: ``t -> w(t)``, one Ornstein–Uhlenbeck process per axis.

    ``w_i(t) = mu_i + sigma_i z_i(t)``, with ``z_i`` a stationary Ornstein–Uhlenbeck
    process of unit variance and correlation time ``T_i``
    (``E[z_i(t) z_i(t + s)] = exp(-|s| / T_i)``), drawn from `key` by its exact
    discretisation on the grid ``t = 0, h, 2h, ..., >= duration`` and interpolated
    linearly in ``t`` (held at the end values outside the grid). A `Gust` is a pytree:
    ``jax.vmap(lambda k: Gust(..., key=k))(keys)`` builds a batch of independent gusts,
    and it goes to `scenes.quadrotor` as ``wind=``. For Dryden's longitudinal gust of
    MIL-F-8785C, with scale length ``L`` at airspeed ``V``, take ``T = L / V``. A batch
    reads each run's path at a computed index, one gather per read, in the engine's
    scalarized program (the gradient of a batch: up to the policy's
    ``scalarize_table_max`` grid points, 128); ``benchmarks/vehicle.py`` measures it.

    Between grid points the interpolated variance is ``sigma^2 (1 - 2 u (1 - u) (1 - a))``
    (``u`` the fraction of the way, ``a = exp(-h / T)``): at most ``h / (2 T)`` less
    than ``sigma^2``; the default ``h = T / 20`` keeps it within 2.5 %.

    **Arguments:**

    - `mean`: ``mu``, the mean wind in m/s, world frame, a scalar or shape `(3,)`.
    - `intensity`: ``sigma``, the standard deviation per axis in m/s (>= 0), a scalar
      or shape `(3,)`.
    - `correlation_time`: ``T`` in s (> 0), a scalar or shape `(3,)`.
    - `duration`: the span of time the path covers, in s (> 0).
    - `key`: a JAX PRNG key (`jax.random.key` or `jax.random.PRNGKey`); the same key
      gives the same gust.
    - `step`: ``h``, the grid step in s (> 0); default the shortest ``T`` over 20.
    - `dtype`: float dtype of the gust (default JAX's default float; `scenes.quadrotor`
      casts it to the scene's).

    `mean`, `intensity`, `correlation_time`, `duration` and `step` must be concrete
    (they fix the size of the grid); `key` may be traced. Bad values raise a
    ``ValueError`` naming the argument.

    **Fields:** `mean` and `intensity` (shape `(3,)`), `step` (shape `()`) and `path`,
    the standardised values ``z`` on the grid, shape `(n + 1, 3)`.

    References: U.S. Department of Defense, MIL-F-8785C, "Flying Qualities of Piloted
    Airplanes", 1980, sec. 3.7 (Dryden spectra); D. T. Gillespie, Phys. Rev. E 54, 2084
    (1996) (the exact update).
    """

    mean: Array
    intensity: Array
    step: Array
    path: Array

    __repr__ = module_repr

    def __init__(
        self,
        mean: ArrayLike = 0.0,
        intensity: ArrayLike = 1.0,
        correlation_time: ArrayLike = 1.0,
        *,
        duration: float,
        key,
        step: float | None = None,
        dtype=None,
    ):
        dtype = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
        mu = _per_axis(mean, "mean", None)
        sigma = _per_axis(intensity, "intensity", 0.0)
        T = _per_axis(correlation_time, "correlation_time", 0.0, strict=True)
        duration = float(duration)
        if not (math.isfinite(duration) and duration > 0):
            raise ValueError(f"duration must be positive and finite (s), got {duration}")
        h = float(T.min()) / _STEPS_PER_CORRELATION_TIME if step is None else float(step)
        if not (math.isfinite(h) and h > 0):
            raise ValueError(f"step must be positive and finite (s), got {h}")
        n = max(1, math.ceil(duration / h - 1e-9))
        if isinstance(key, int):
            key = jax.random.key(key)
        a = np.exp(-h / T).astype(dtype)
        self.mean = jnp.asarray(mu, dtype)
        self.intensity = jnp.asarray(sigma, dtype)
        self.step = jnp.asarray(h, dtype)
        self.path = _ou_path(key, jnp.asarray(a), n, dtype)

    @property
    def times(self) -> Array:
        """The grid times ``k h``, shape `(n + 1,)`."""
        return self.step * jnp.arange(self.path.shape[-2], dtype=self.step.dtype)

    def __call__(self, t) -> Array:
        """The wind velocity ``w(t)`` in m/s, world frame, shape ``t.shape + (3,)``."""
        t = jnp.asarray(t, self.step.dtype)
        last = self.path.shape[-2] - 1
        s = jnp.clip(t / self.step, 0.0, float(last))
        i = jnp.clip(jnp.floor(s), 0.0, float(last - 1))
        u = (s - i)[..., None]
        i = i.astype(jnp.int32)
        z = self.path[i] * (1.0 - u) + self.path[i + 1] * u
        return self.mean + self.intensity * z
