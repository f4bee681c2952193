"""Sensor noise: the state a sampled controller sees.

At the sample ``k`` (time ``t_k = k T``, ``T`` the control period) the controller
reads, in place of the true state,

    R_seen = R exp(hat(xi_R)),   Omega_seen = Omega + xi_Omega,
    x_seen = x + xi_x,           v_seen = v + xi_v,

with independent Gaussian ``xi ~ N(0, diag(sigma^2))`` per axis: the attitude error
is a Gaussian tangent in the body frame (the "concentrated Gaussian" on SO(3) of
Barfoot & Furgale), the others additive. The plant is not perturbed.

The draws are counter-based: the twelve numbers of sample ``k`` are the Threefry-2x32
hash of the counters ``(j, k)`` under the key's two words (`threefry2x32`), each
word's top 24 bits a uniform ``u`` and ``sqrt(2) erfinv(2 u - 1)`` its normal (by
Giles' approximation, `_normals`). A run
is reproducible from its key, whatever the integrator or the number of steps per hold,
and the draws are elementwise integer arithmetic, which a batch runs in the engine's
scalarized program (random primitives would not be).

References: T. D. Barfoot, P. T. Furgale, "Associating uncertainty with
three-dimensional poses for use in estimation problems", IEEE T-RO 30(3), 2014;
J. K. Salmon, M. A. Moraes, R. O. Dror, D. E. Shaw, "Parallel random numbers: as easy
as 1, 2, 3", SC 2011 (Threefry).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._repr import module_repr
from ._so3 import _as_float, _exp, _is_concrete, _mm, _to_dtype
from ._types import Array, ArrayLike

_FIELDS = ("attitude", "rate", "position", "velocity")
_UNITS = {"attitude": "rad", "rate": "rad/s", "position": "m", "velocity": "m/s"}


_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))  # Threefry-2x32's, Salmon et al. Table 4


def _rotl(x, r: int):
    return (x << np.uint32(r)) | (x >> np.uint32(32 - r))


def threefry2x32(k0, k1, x0, x1):
    """Threefry-2x32 with 20 rounds (Salmon et al., SC 2011): the pair of uint32 words
    ``(x0, x1)`` hashed under the key ``(k0, k1)``; elementwise, so any broadcastable
    shapes. The same function as JAX's own ``threefry_2x32``."""
    k0, k1, x0, x1 = (jnp.asarray(a, jnp.uint32) for a in (k0, k1, x0, x1))
    ks = (k0, k1, k0 ^ k1 ^ np.uint32(0x1BD11BDA))
    x0, x1 = x0 + ks[0], x1 + ks[1]
    for i in range(5):
        for r in _ROTATIONS[i % 2]:
            x0 = x0 + x1
            x1 = _rotl(x1, r) ^ x0
        x0 = x0 + ks[(i + 1) % 3]
        x1 = x1 + ks[(i + 2) % 3] + np.uint32(i + 1)
    return x0, x1


def _key_words(key):
    """The key's first two uint32 words (a typed key's data, or a raw ``PRNGKey``)."""
    if jax.dtypes.issubdtype(jnp.result_type(key), jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    return key[..., 0], key[..., 1]


#: Giles' single-precision approximation of ``erfinv`` (M. Giles, "Approximating the
#: erfinv function", GPU Computing Gems Jade Edition, 2011): with ``w = -log(1 - x^2)``,
#: ``erfinv(x) = x p(w - 2.5)`` for ``w < 5`` and ``x q(sqrt(w) - 3)`` otherwise, ``p``
#: and ``q`` of degree 8 (coefficients from the highest power down). Relative error
#: below 2e-7 (`tests/test_sensor_noise.py` checks it against SciPy's ``erfinv``).
_GILES_P = (2.81022636e-08, 3.43273939e-07, -3.5233877e-06, -4.39150654e-06, 0.00021858087,
            -0.00125372503, -0.00417768164, 0.246640727, 1.50140941)  # fmt: skip
_GILES_Q = (-0.000200214257, 0.000100950558, 0.00134934322, -0.00367342844, 0.00573950773,
            -0.0076224613, 0.00943887047, 1.00167406, 2.83297682)  # fmt: skip


def _normals(key, k, shape: tuple[int, ...], dtype):
    """Standard normals of ``shape`` for sample ``k`` (`threefry2x32` of ``(j, k)``).

    Each word's top 24 bits ``m`` give ``x = 2 u - 1 = (a - 2^24) 2^-24`` with
    ``a = 2 m + 1``, never ``±1``, and ``1 - x^2 = a (2^25 - a) 2^-48``, whose logarithm
    is taken of the integer product (exact in float64: no cancellation near ``±1``). The
    normal is ``sqrt(2) erfinv(x)`` by Giles' approximation (`_GILES_P`), plain
    arithmetic and one ``log`` and ``sqrt`` in ``dtype``: in float64 it costs about half
    of JAX's ``erfinv`` (``benchmarks/vehicle.py``, ``noise``), whose precision the
    24-bit uniform would not use.
    """
    n = int(np.prod(shape))
    j = np.arange(-(-n // 2), dtype=np.uint32)
    k0, k1 = _key_words(key)
    w0, w1 = threefry2x32(k0, k1, j, jnp.asarray(k).astype(jnp.uint32))
    return _gaussian(jnp.concatenate([w0, w1])[:n], dtype).reshape(shape)


def _gaussian(words, dtype):
    """The standard normals of uint32 ``words`` (`_normals`), in ``dtype``."""
    a = 2 * (words >> np.uint32(8)).astype(jnp.int32) + 1
    x = (a - 2**24).astype(dtype) * (2.0**-24)
    w = 48 * math.log(2.0) - jnp.log(a.astype(dtype) * (2**25 - a).astype(dtype))
    centre, tail = w - 2.5, jnp.sqrt(jnp.maximum(w, 5.0)) - 3.0
    p, q = _GILES_P[0], _GILES_Q[0]
    for cp, cq in zip(_GILES_P[1:], _GILES_Q[1:], strict=True):
        p, q = cp + p * centre, cq + q * tail
    return (math.sqrt(2.0) * jnp.where(w < 5.0, p, q) * x).astype(dtype)


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
    ``xi_* ~ N(0, sigma_*^2)`` independent per axis, drawn from the key and ``k``
    (counter-based, `threefry2x32`). Pass it as ``noise=`` to `scenes.quadrotor` or
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
        ``sigma * N(0, 1)``, counter-based from the key and ``k`` (the module's docstring).
        """
        k = jnp.round(jnp.asarray(t, dtype) / period).astype(jnp.int32)
        z = _normals(self.key, k, (*batch, 4, 3), dtype)
        return tuple(
            jnp.asarray(getattr(self, name), dtype) * z[..., i, :] for i, name in enumerate(_FIELDS)
        )

    def unwrapped(self) -> SensorNoise:
        """The same noise with its key as raw uint32 words: what a step reads, so that the
        loop holds no typed key (a run's scene, `Scene.for_step`)."""
        if not jax.dtypes.issubdtype(jnp.result_type(self.key), jax.dtypes.prng_key):
            return self
        return eqx.tree_at(lambda n: n.key, self, jax.random.key_data(self.key))

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
