"""SO(3) primitives: hat/vee, exp/log, Jacobians, conversions, sampling, errors.

Conventions: rotations are ``(..., 3, 3)``, vectors ``(..., 3)``, quaternions
scalar-first ``(..., 4)`` as ``(w, x, y, z)``. Every function broadcasts over
leading axes and works under ``jit``, ``vmap`` and ``grad`` in float32 and float64.

Singular-looking formulas (``sin(t)/t`` and friends) are evaluated with the
"two ``where``s" pattern: the argument is first made safe, then a Taylor series
or the closed form is selected, so that values *and* derivatives are finite and
accurate at ``theta = 0`` and near ``theta = pi``. The Taylor cut-offs depend on
the dtype (see `_cutoff`): below them the closed form would lose digits to
cancellation, above them the (9-term) series has a truncation error below
machine epsilon.

Input checking: wrong trailing shapes raise ``ValueError`` at trace time.
Value checks (NaN/inf input, zero-norm quaternion or axis, ``det <= 0`` in
`project`) raise ``ValueError`` only when the call is *eager* (concrete
arrays); under ``jit``/``vmap``/``grad`` such input yields NaN in the output,
which `so3jax.simulate` reports in its status.
"""

from __future__ import annotations

import functools
import math
from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np

from ._types import Array, ArrayLike, Mat3, Quat, Rot, Scalar, Vec3

# --------------------------------------------------------------------------
# Input handling
# --------------------------------------------------------------------------


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _as_float(x: ArrayLike) -> Array:
    # NumPy values, Python floats and flat sequences of them go to the device as they
    # are: `jnp.asarray` compiles a program for every new shape on first use (JAX 0.10).
    if isinstance(x, list | tuple) and x and all(isinstance(v, float) for v in x):
        x = np.asarray(x)
    x = jax.device_put(x) if isinstance(x, np.ndarray | np.generic | float) else jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _to_dtype(x: ArrayLike, dtype) -> Array:
    """``jnp.asarray(x, dtype)``, in NumPy when ``x`` is concrete (no program to compile)."""
    return jax.device_put(np.asarray(x, dtype)) if _is_concrete(x) else jnp.asarray(x, dtype)


def _prep(x: ArrayLike, name: str, trailing: tuple[int, ...]) -> Array:
    """Convert to a float array, check its trailing shape, and (eagerly) finiteness."""
    x = _as_float(x)
    k = len(trailing)
    if x.ndim < k or tuple(x.shape[x.ndim - k :]) != trailing:
        want = "(..., " + ", ".join(map(str, trailing)) + ")"
        raise ValueError(f"{name} must have shape {want}, got shape {tuple(x.shape)}")
    # NumPy, not jnp: under an active jit trace jnp ops on concrete arrays are staged.
    if _is_concrete(x) and not np.all(np.isfinite(np.asarray(x))):
        raise ValueError(f"{name} contains NaN or inf")
    return x


# Eager value checks run in NumPy on the concrete array: `jnp` ops on a concrete
# constant inside a trace (a `lax.scan`/`cond` body, `eqx.filter_jit`) are staged,
# and `bool()` of the result would raise a TracerBoolConversionError.


def _np_norm2(x: Array) -> np.ndarray:
    x = np.asarray(x)
    return np.sum(x * x, axis=-1)


def _np_det(A: Array) -> np.ndarray:
    A = np.asarray(A)
    return np.sum(A[..., 0, :] * np.cross(A[..., 1, :], A[..., 2, :]), axis=-1)


def _common_dtype(*xs: Array):
    return jnp.result_type(*xs)


# --------------------------------------------------------------------------
# Small dense helpers, written elementwise so that XLA fuses them (batched 3x3
# `dot`s are slow on CPU under vmap).
# --------------------------------------------------------------------------


#: The precision of every contraction (``dot_general``) so3jax writes: in float32 on a GPU,
#: JAX's default is TF32 (about three decimal digits), which a step on the group cannot
#: afford. A CPU computes every precision alike (`tests/test_precision.py`).
_FULL = jax.lax.Precision.HIGHEST


def _mm(A: Array, B: Array) -> Array:
    """``A @ B`` for (..., 3, 3) arrays, as a fused multiply-add."""
    return jnp.sum(A[..., :, :, None] * B[..., None, :, :], axis=-2)


def _mv(A: Array, v: Array) -> Array:
    """``A @ v`` for (..., 3, 3) and (..., 3)."""
    return jnp.sum(A * v[..., None, :], axis=-1)


def _mtv(A: Array, v: Array) -> Array:
    """``A.T @ v`` for (..., 3, 3) and (..., 3)."""
    return jnp.sum(A * v[..., :, None], axis=-2)


def _mT(A: Array) -> Array:
    return jnp.swapaxes(A, -1, -2)


def _cross(a: Array, b: Array) -> Array:
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _dot(a: Array, b: Array) -> Array:
    return jnp.sum(a * b, axis=-1)


def _det(A: Array) -> Array:
    return _dot(A[..., 0, :], _cross(A[..., 1, :], A[..., 2, :]))


def _eye_like(x: Array, batch: tuple[int, ...]) -> Array:
    return jnp.broadcast_to(jnp.eye(3, dtype=x.dtype), batch + (3, 3))


# --------------------------------------------------------------------------
# Series and cut-offs
# --------------------------------------------------------------------------

_NTERMS = 9


def _series(coeffs_fn) -> np.ndarray:
    return np.array([float(coeffs_fn(k)) for k in range(_NTERMS)])


# A(t) = sin(th)/th, B = (1 - cos th)/th^2, C = (th - sin th)/th^3, t = th^2.
_A_SERIES = _series(lambda k: Fraction((-1) ** k, math.factorial(2 * k + 1)))
_B_SERIES = _series(lambda k: Fraction((-1) ** k, math.factorial(2 * k + 2)))
_C_SERIES = _series(lambda k: Fraction((-1) ** k, math.factorial(2 * k + 3)))
# D(t) = (1 - (th/2) cot(th/2)) / th^2 = sum_{n>=1} |B_2n| t^(n-1) / (2n)!
# (Bernoulli numbers; Abramowitz & Stegun 4.3.70).
_BERNOULLI_ABS = [
    Fraction(1, 6),
    Fraction(1, 30),
    Fraction(1, 42),
    Fraction(1, 30),
    Fraction(5, 66),
    Fraction(691, 2730),
    Fraction(7, 6),
    Fraction(3617, 510),
    Fraction(43867, 798),
]
_D_SERIES = _series(lambda k: _BERNOULLI_ABS[k] / math.factorial(2 * k + 2))
# atan(r)/r = sum (-1)^k r^(2k) / (2k+1), in s = r^2 (used by `log` near 0).
_ATAN_SERIES = np.array([(-1) ** k / (2 * k + 1) for k in range(12)])


def _cutoff(dtype) -> float:
    """Threshold on ``theta^2`` below which the Taylor series are used.

    Chosen so that the 9-term series is exact to machine precision below it and
    the closed forms (whose cancellation costs about ``12 eps / theta^2`` for C
    and D) are accurate above it: 0.5 in float64, 4.0 in float32 and lower
    precisions.

    float64: the D series converges like ``(t / 4 pi^2)^n``; its first omitted
    term is ~1e-15 relative at ``t = 1`` but ~1e-18 at ``t = 0.5``, where the
    closed forms are already good to ~3e-15 (checked against mpmath in
    tests/test_so3.py). float32: at the former cut-off 1.0 the closed form of
    D was off by ~1e-6 (8 ulp); the series is exact to float32 precision up to
    ``t = 4`` (first omitted term ~1e-10), where the closed forms lose at most
    ~1 ulp, so the worst error over ``[0, pi]`` drops to ~1.5e-7.
    """
    return 0.5 if jnp.finfo(dtype).bits >= 64 else 4.0


def _atan_cutoff(dtype) -> float:
    return 1e-2 if jnp.finfo(dtype).bits >= 64 else 3e-2


def _polyval(coeffs: np.ndarray, t: Array) -> Array:
    # Horner's rule. The coefficients go in as Python floats (weakly typed): a
    # NumPy float64 scalar would promote float32 input to float64 under x64.
    out = jnp.full_like(t, float(coeffs[-1]))
    for c in coeffs[-2::-1]:
        out = out * t + float(c)
    return out


def _safe_theta(t: Array, cutoff: float) -> tuple[Array, Array, Array]:
    """``(small, ts, th)``: where ``t < cutoff``, and ``t`` and ``theta`` made safe there.

    ``ts`` is ``t`` with 1 below the cut-off, so the closed forms (and their
    derivatives) stay finite on the branch ``where`` discards.
    """
    small = t < cutoff
    ts = jnp.where(small, jnp.ones_like(t), t)
    return small, ts, jnp.sqrt(ts)


# ``sin`` and ``cos`` for the coefficient functions, vectorisable. XLA on CPU lowers
# jnp.sin and jnp.cos to a scalar call per element, several times the cost of the code
# below, and each exponential update takes two sines. Here: Cody and Waite's reduction
# x = k pi/2 + r, |r| <= pi/4, with pi/2 split into pieces whose products with k are
# exact (float64: the 33-bit pieces of fdlibm's e_rem_pio2.c; float32: those of
# Cephes' sinf.c, doubled), then Taylor polynomials in r^2 (their first omitted
# term is below 5e-17 relative at pi/4 in float64, 2e-10 in float32), and the
# quadrant k mod 4 picks the signs and which polynomial is which. Accurate to an
# ulp or two while |x| < 1e5 (checked against NumPy in tests/test_so3.py); the
# reduction loses digits beyond that, far past any angle one time step turns.
_SIN_TAIL = {
    bits: np.array([(-1) ** (k + 1) / math.factorial(2 * k + 3) for k in range(n)])
    for bits, n in ((64, 7), (32, 4))
}
_COS_TAIL = {
    bits: np.array([(-1) ** k / math.factorial(2 * k + 4) for k in range(n)])
    for bits, n in ((64, 7), (32, 4))
}
_PIO2_PIECES = {
    64: (1.57079632673412561417e00, 6.07710050630396597660e-11, 2.02226624879595063154e-21),
    32: (1.5703125, 4.837512969970703125e-4, 7.54978995489188216e-8),
}


@jax.custom_jvp
def _sincos(x: Array) -> tuple[Array, Array]:
    """``(sin x, cos x)`` by range reduction and polynomials (see `_SIN_TAIL`).

    Float64 and float32; other precisions fall back to ``jnp.sin`` / ``jnp.cos``.
    """
    bits = jnp.finfo(x.dtype).bits
    if bits not in _PIO2_PIECES:
        return jnp.sin(x), jnp.cos(x)
    p1, p2, p3 = _PIO2_PIECES[bits]
    k = jnp.round(x * (2.0 / math.pi))
    r = ((x - k * p1) - k * p2) - k * p3
    r2 = r * r
    s = r + r * r2 * _polyval(_SIN_TAIL[bits], r2)
    c = (1.0 - 0.5 * r2) + r2 * r2 * _polyval(_COS_TAIL[bits], r2)
    q = k - 4.0 * jnp.floor(0.25 * k)  # k mod 4, exact in floating point
    odd = (q == 1.0) | (q == 3.0)
    sin_x, cos_x = jnp.where(odd, c, s), jnp.where(odd, s, c)
    sin_x = jnp.where(q >= 2.0, -sin_x, sin_x)
    cos_x = jnp.where((q == 1.0) | (q == 2.0), -cos_x, cos_x)
    return sin_x, cos_x


@_sincos.defjvp
def _sincos_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    s, c = _sincos(x)
    return (s, c), (c * dx, -s * dx)


def _closed_AB(th: Array) -> tuple[Array, Array]:
    """``A = sin(th)/th`` and ``B = 2 sin^2(th/2)/th^2`` from one half-angle ``sincos``.

    ``A = s c / h`` and ``B = (s / h)^2 / 2`` with ``h = th/2``, ``(s, c) = (sin h,
    cos h)``: one reduction and one division for both. B written this way has no
    cancellation, unlike ``(1 - cos th) / th^2``.
    """
    h = 0.5 * th
    s, c = _sincos(h)
    u = s / h
    return u * c, 0.5 * u * u


def _coeffs(t: Array, which: str) -> Array:
    """Evaluate one of the coefficient functions A, B, C, D at ``t = theta^2``."""
    small, ts, th = _safe_theta(t, _cutoff(t.dtype))
    if which == "A":
        series, closed = _A_SERIES, _closed_AB(th)[0]
    elif which == "B":
        series, closed = _B_SERIES, _closed_AB(th)[1]
    elif which == "C":
        series, closed = _C_SERIES, (th - _sincos(th)[0]) / (ts * th)
    elif which == "D":
        half = 0.5 * th
        s, c = _sincos(half)
        # (1 + cos th) / (2 th sin th) written as cot(th/2) / (2 th): finite at th = pi.
        series, closed = _D_SERIES, (1.0 - half * c / s) / ts
    else:  # pragma: no cover
        raise AssertionError(which)
    return jnp.where(small, _polyval(series, t), closed)


# --------------------------------------------------------------------------
# hat / vee, algebra and group actions
# --------------------------------------------------------------------------


def _hat(w: Array) -> Array:
    z = jnp.zeros_like(w[..., 0])
    w0, w1, w2 = w[..., 0], w[..., 1], w[..., 2]
    return jnp.stack(
        [
            jnp.stack([z, -w2, w1], axis=-1),
            jnp.stack([w2, z, -w0], axis=-1),
            jnp.stack([-w1, w0, z], axis=-1),
        ],
        axis=-2,
    )


def _vee(W: Array) -> Array:
    return 0.5 * jnp.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]],
        axis=-1,
    )


# Jitted cores behind the public functions: an eager call then runs one compiled
# program instead of dozens of dispatched operations, each compiled on its first use
# (checks stay outside). Every public function below has one.
_hat_jit = jax.jit(_hat)
_vee_jit = jax.jit(_vee)
_cross_jit = jax.jit(_cross)
_mv_jit = jax.jit(_mv)


def hat(w: Vec3) -> Mat3:
    """Skew-symmetric matrix of a vector: ``hat(w) @ v = w x v``.

    **Arguments:**

    - `w`: vector, shape `(..., 3)`.

    **Returns:** skew-symmetric matrix, shape `(..., 3, 3)`.
    """
    return _hat_jit(_prep(w, "w", (3,)))


def vee(W: Mat3) -> Vec3:
    """Inverse of `hat`: ``vee(hat(w)) = w``.

    For a matrix that is not skew-symmetric this returns the vector of its
    skew part ``(W - W^T) / 2``.

    **Arguments:**

    - `W`: matrix, shape `(..., 3, 3)`.

    **Returns:** vector, shape `(..., 3)`.
    """
    return _vee_jit(_prep(W, "W", (3, 3)))


def bracket(x: Vec3, y: Vec3) -> Vec3:
    """Lie bracket of so(3) in vector form: ``[hat x, hat y] = hat(x cross y)``.

    **Arguments:**

    - `x`, `y`: vectors, shape `(..., 3)`.

    **Returns:** ``x cross y``, shape `(..., 3)`.
    """
    return _cross_jit(_prep(x, "x", (3,)), _prep(y, "y", (3,)))


def adjoint(R: Rot, w: Vec3) -> Vec3:
    """Adjoint action of SO(3) on so(3) in vector form: ``Ad_R w = R w``.

    Equivalently ``R hat(w) R^T = hat(R w)``.

    **Arguments:**

    - `R`: rotation, shape `(..., 3, 3)`.
    - `w`: vector, shape `(..., 3)`.

    **Returns:** ``R w``, shape `(..., 3)`.
    """
    return _mv_jit(_prep(R, "R", (3, 3)), _prep(w, "w", (3,)))


def coadjoint(R: Rot, M: Vec3) -> Vec3:
    """Coadjoint action of SO(3) on so(3)* ~ R^3 (momenta): ``Ad*_R M = R M``.

    With the dual pairing given by the dot product, the coadjoint orbits are
    spheres ``|M| = const`` (the Casimir of the free rigid body).

    **Arguments:**

    - `R`: rotation, shape `(..., 3, 3)`.
    - `M`: momentum, shape `(..., 3)`.

    **Returns:** ``R M``, shape `(..., 3)`.
    """
    return _mv_jit(_prep(R, "R", (3, 3)), _prep(M, "M", (3,)))


# --------------------------------------------------------------------------
# exp / log and Jacobians
# --------------------------------------------------------------------------


def _exp(w: Array) -> Array:
    t = _dot(w, w)
    A = _coeffs(t, "A")[..., None, None]
    B = _coeffs(t, "B")[..., None, None]
    # hat(w)^2 = w w^T - |w|^2 I, so R = (1 - B t) I + A hat(w) + B w w^T.
    eye = _eye_like(w, w.shape[:-1])
    wwT = w[..., :, None] * w[..., None, :]
    return (1.0 - B * t[..., None, None]) * eye + A * _hat(w) + B * wwT


_exp_jit = jax.jit(_exp)


def _right_jacobian_times(w: Array, v: Array, B: Array, C: Array) -> Array:
    """``J_r(w) v = v - B w x v + C w x (w x v)`` (coefficients from `_abc_coeffs`)."""
    wxv = _cross(w, v)
    return v - B[..., None] * wxv + C[..., None] * _cross(w, wxv)


def _expm1_from(w: Array, t: Array, A: Array, B: Array) -> Array:
    """``exp(w) - I = A hat(w) + B (w w^T - t I)`` given ``t = |w|^2`` and A, B."""
    wwT = w[..., :, None] * w[..., None, :]
    A, B = A[..., None, None], B[..., None, None]
    return A * _hat(w) + B * (wwT - t[..., None, None] * _eye_like(w, w.shape[:-1]))


def _expm1_raw(w: Array) -> Array:
    t = _dot(w, w)
    return _expm1_from(w, t, *_ab_coeffs(t))


# A = sin(th)/th and B = 2 (sin(th/2)/th)^2 lose no digits to cancellation at any angle,
# unlike C and D, so the group updates need their series (kept because th = sqrt(t) has
# no safe derivative at 0) only far closer to 0, and 4 terms of it instead of 9: the
# first omitted term is t^4/9! < 3e-22 below 1e-4 (float64) and < 3e-14 below 1e-2.
_AB_NTERMS = 4


def _ab_cutoff(dtype) -> float:
    return 1e-4 if jnp.finfo(dtype).bits >= 64 else 1e-2


def _ab_coeffs(t: Array) -> tuple[Array, Array]:
    """``(A, B)`` at ``t = theta^2`` for the exponential's updates (see `_AB_NTERMS`)."""
    small, _, th = _safe_theta(t, _ab_cutoff(t.dtype))
    A_closed, B_closed = _closed_AB(th)
    A = jnp.where(small, _polyval(_A_SERIES[:_AB_NTERMS], t), A_closed)
    B = jnp.where(small, _polyval(_B_SERIES[:_AB_NTERMS], t), B_closed)
    return A, B


def _abc_coeffs(t: Array) -> tuple[Array, Array, Array]:
    """``(A, B, C)`` at ``t = theta^2`` for the derivative rules, from one ``sincos``.

    A and B as in `_ab_coeffs`. ``C = (th - sin th) / th^3 = (1 - A) / t`` loses
    digits to cancellation near 0 (about ``12 eps`` at the cut-off), so it takes
    the 9-term series below `_cutoff` as `_coeffs` does; above it, ``1 - A`` from
    the same closed form of A. One sine and cosine for all three: every
    coefficient is taken at the one cut-off.
    """
    A, B = _ab_coeffs(t)
    small_c, ts, _ = _safe_theta(t, _cutoff(t.dtype))
    return A, B, jnp.where(small_c, _polyval(_C_SERIES, t), (1.0 - A) / ts)


def _expm1_for_rules(w: Array) -> tuple[Array, Array, Array]:
    """``(exp(w) - I, B, C)``: what both derivative rules of the exponential need."""
    t = _dot(w, w)
    A, B, C = _abc_coeffs(t)
    return _expm1_from(w, t, A, B), B, C


def _times_expm1(M: Array, w: Array, A: Array, B: Array) -> Array:
    """``M (exp(w) - I) = A M hat(w) + B M hat(w)^2`` from row cross products.

    Row ``i`` of ``M hat(w)`` is ``m_i x w``: 54 operations for the two
    products and 27 for the sum, against about 100 for forming ``exp(w) - I``
    and multiplying.
    """
    ww = w[..., None, :]
    X = _cross(M, ww)
    return A[..., None, None] * X + B[..., None, None] * _cross(X, ww)


def _cay_increment_raw(R: Array, u: Array) -> Array:
    uu = u[..., None, :]
    X = _cross(R, uu)  # R hat(u)
    Y = _cross(X, uu)  # R hat(u)^2
    c = (4.0 / (4.0 + _dot(u, u)))[..., None, None]
    return c * (X + 0.5 * Y)


def _dcayinv(u: Array, v: Array) -> Array:
    """Inverse right-trivialised derivative of the Cayley map.

    For ``R = R0 cay(u)`` and ``R' = R hat(v)``: ``u' = v + 1/2 u x v + 1/4 (u . v) u``
    (from ``dcay^-1_U(H) = (I - U/2) H (I + U/2)``, Iserles, Munthe-Kaas, Nørsett,
    Zanna, Acta Numer. 9 (2000), sec. 8.3, transposed to the body frame).
    """
    return v + 0.5 * _cross(u, v) + 0.25 * _dot(u, v)[..., None] * u


def exp(w: Vec3) -> Rot:
    """Exponential map so(3) -> SO(3) (Rodrigues' formula).

    ``exp(w) = I + sin(th)/th hat(w) + (1 - cos th)/th^2 hat(w)^2``, ``th = |w|``.

    **Arguments:**

    - `w`: rotation vector, shape `(..., 3)`.

    **Returns:** rotation matrix, shape `(..., 3, 3)`.
    """
    return _exp_jit(_prep(w, "w", (3,)))


def _to_quat(R: Array) -> Array:
    # Shepperd's method (J. Guidance & Control 1(3), 1978): pick the largest of
    # 4w^2, 4x^2, 4y^2, 4z^2 (all computable from the diagonal) as the pivot.
    # All four candidates use the same square root s = sqrt(max) >= 1, so no
    # branch ever takes the square root of a negative number (safe under grad).
    R00, R01, R02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    R10, R11, R12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    R20, R21, R22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    tr = R00 + R11 + R22
    d = jnp.stack([1.0 + tr, 1.0 + 2 * R00 - tr, 1.0 + 2 * R11 - tr, 1.0 + 2 * R22 - tr], -1)
    i = jnp.argmax(d, axis=-1)
    dmax = jnp.max(d, axis=-1)
    s = jnp.sqrt(jnp.where(dmax > 0, dmax, 1.0))
    h = 0.5 * s
    inv = 0.5 / s
    a, b, c = (R21 - R12) * inv, (R02 - R20) * inv, (R10 - R01) * inv
    e, f, g = (R01 + R10) * inv, (R02 + R20) * inv, (R12 + R21) * inv
    q0 = jnp.stack([h, a, b, c], -1)
    q1 = jnp.stack([a, h, e, f], -1)
    q2 = jnp.stack([b, e, h, g], -1)
    q3 = jnp.stack([c, f, g, h], -1)
    i = i[..., None]
    q = jnp.where(i == 0, q0, jnp.where(i == 1, q1, jnp.where(i == 2, q2, q3)))
    q = jnp.where(q[..., :1] < 0, -q, q)
    q = q / jnp.sqrt(_dot(q, q))[..., None]
    return jnp.where((dmax > 0)[..., None], q, jnp.nan)


def _log_from_quat(q: Array) -> Array:
    # q = (cos(th/2), sin(th/2) u) with w >= 0, so th = 2 atan2(|v|, w) in [0, pi]
    # and log R = th u = (2 atan2(|v|, w) / |v|) v.
    w, v = q[..., 0], q[..., 1:]
    n2 = _dot(v, v)
    small = n2 < _atan_cutoff(q.dtype) * w * w  # (|v| / w)^2 small: th small
    w_s = jnp.where(small, w, 1.0)
    n_s = jnp.sqrt(jnp.where(small, 1.0, n2))
    series = 2.0 / w_s * _polyval(_ATAN_SERIES, n2 / (w_s * w_s))
    closed = 2.0 * jnp.arctan2(n_s, w) / n_s
    return jnp.where(small, series, closed)[..., None] * v


_to_quat_jit = jax.jit(_to_quat)


def _log(R: Array) -> Array:
    return _log_from_quat(_to_quat(R))


_log_jit = jax.jit(_log)


def log(R: Rot) -> Vec3:
    """Logarithm SO(3) -> so(3): the rotation vector ``w`` with ``|w| <= pi``.

    Computed through a largest-pivot (Shepperd) quaternion and ``atan2``, which
    is accurate at every angle (``arccos`` of the trace loses half the digits
    near 0 and pi). At exactly ``pi`` the sign of ``w`` is a convention.

    **Arguments:**

    - `R`: rotation matrix, shape `(..., 3, 3)`.

    **Returns:** rotation vector, shape `(..., 3)`.
    """
    return _log_jit(_prep(R, "R", (3, 3)))


def _jac(w: Array, sign_b: float, which_b: str, which_c: str, b_const: float | None) -> Array:
    t = _dot(w, w)
    C = _coeffs(t, which_c)[..., None, None]
    B = (b_const if b_const is not None else _coeffs(t, which_b)[..., None, None]) * sign_b
    W = _hat(w)
    eye = _eye_like(w, w.shape[:-1])
    wwT = w[..., :, None] * w[..., None, :]
    return eye + B * W + C * (wwT - t[..., None, None] * eye)


_jac_jit = jax.jit(_jac, static_argnums=(1, 2, 3, 4))


def left_jacobian(w: Vec3) -> Mat3:
    """Left Jacobian of SO(3): ``J_l(w) = I + B hat(w) + C hat(w)^2``.

    ``B = (1 - cos th)/th^2``, ``C = (th - sin th)/th^3``; ``exp(w + dw) ~
    exp(J_l(w) dw) exp(w)``.

    **Arguments:**

    - `w`: rotation vector, shape `(..., 3)`.

    **Returns:** shape `(..., 3, 3)`.

    References: G. S. Chirikjian, *Stochastic Models, Information Theory, and
    Lie Groups*, vol. 2, Birkhauser 2011, sec. 10.6.
    """
    return _jac_jit(_prep(w, "w", (3,)), 1.0, "B", "C", None)


def right_jacobian(w: Vec3) -> Mat3:
    """Right Jacobian of SO(3): ``J_r(w) = J_l(-w) = I - B hat(w) + C hat(w)^2``.

    ``d/dt exp(w) = exp(w) hat(J_r(w) w')``.

    **Arguments:**

    - `w`: rotation vector, shape `(..., 3)`.

    **Returns:** shape `(..., 3, 3)`.
    """
    return _jac_jit(_prep(w, "w", (3,)), -1.0, "B", "C", None)


def left_jacobian_inv(w: Vec3) -> Mat3:
    """Inverse left Jacobian: ``I - 1/2 hat(w) + D hat(w)^2``.

    ``D = (1 - (th/2) cot(th/2)) / th^2``, finite for ``th < 2 pi``.

    **Arguments:**

    - `w`: rotation vector, shape `(..., 3)`.

    **Returns:** shape `(..., 3, 3)`.
    """
    return _jac_jit(_prep(w, "w", (3,)), -1.0, "", "D", 0.5)


def right_jacobian_inv(w: Vec3) -> Mat3:
    """Inverse right Jacobian: ``I + 1/2 hat(w) + D hat(w)^2`` (the dexp^-1 of RKMK).

    If ``R = R0 exp(u)`` and ``R' = R hat(Omega)`` then ``u' = J_r^-1(u) Omega``.

    **Arguments:**

    - `w`: rotation vector, shape `(..., 3)`.

    **Returns:** shape `(..., 3, 3)`.
    """
    return _jac_jit(_prep(w, "w", (3,)), 1.0, "", "D", 0.5)


def _dexpinv(u: Array, v: Array) -> Array:
    """``J_r^-1(u) v`` without forming the matrix (used by the integrators)."""
    t = _dot(u, u)
    D = _coeffs(t, "D")[..., None]
    uxv = _cross(u, v)
    return v + 0.5 * uxv + D * _cross(u, uxv)


# --------------------------------------------------------------------------
# Quaternions, axis-angle, Euler angles
# --------------------------------------------------------------------------


def _from_quat(q: Array) -> Array:
    n2 = _dot(q, q)
    q = q / jnp.sqrt(n2)[..., None]
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


_from_quat_jit = jax.jit(_from_quat)


def from_quat(q: Quat) -> Rot:
    """Rotation matrix of a quaternion ``(w, x, y, z)`` (normalised first).

    ``q`` and ``-q`` give the same rotation (the double cover S^3 -> SO(3)).
    A zero quaternion is a ``ValueError`` when eager and gives NaN under ``jit``.

    **Arguments:**

    - `q`: quaternion, scalar first, shape `(..., 4)`.

    **Returns:** rotation matrix, shape `(..., 3, 3)`.
    """
    q = _prep(q, "q", (4,))
    if _is_concrete(q) and np.any(_np_norm2(q) == 0):
        raise ValueError("q has zero norm; a quaternion must be non-zero to define a rotation")
    return _from_quat_jit(q)


def to_quat(R: Rot) -> Quat:
    """Unit quaternion ``(w, x, y, z)`` of a rotation, with ``w >= 0``.

    Shepperd's largest-pivot method: accurate at every angle.

    **Arguments:**

    - `R`: rotation matrix, shape `(..., 3, 3)`.

    **Returns:** quaternion, shape `(..., 4)`.
    """
    return _to_quat_jit(_prep(R, "R", (3, 3)))


def quat_multiply(p: Quat, q: Quat) -> Quat:
    """Hamilton product ``p q`` (scalar first); ``from_quat(p q) = from_quat(p) from_quat(q)``.

    **Arguments:**

    - `p`, `q`: quaternions, shape `(..., 4)`.

    **Returns:** shape `(..., 4)`.
    """
    return _quat_multiply(_prep(p, "p", (4,)), _prep(q, "q", (4,)))


@jax.jit
def _quat_multiply(p: Array, q: Array) -> Array:
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    w = pw * qw - _dot(pv, qv)[..., None]
    v = pw * qv + qw * pv + _cross(pv, qv)
    return jnp.concatenate([w, v], -1)


def from_axis_angle(axis: Vec3, angle: Scalar) -> Rot:
    """Rotation by ``angle`` (radians) about ``axis`` (normalised first).

    **Arguments:**

    - `axis`: shape `(..., 3)`, non-zero.
    - `angle`: shape `(...)`, broadcast against the axis' batch shape.

    **Returns:** rotation matrix, shape `(..., 3, 3)`.
    """
    axis = _prep(axis, "axis", (3,))
    angle = _prep(angle, "angle", ())
    if _is_concrete(axis) and np.any(_np_norm2(axis) == 0):
        raise ValueError("axis has zero norm; give a non-zero rotation axis")
    return _from_axis_angle(axis, angle)


@jax.jit
def _from_axis_angle(axis: Array, angle: Array) -> Array:
    u = axis / jnp.sqrt(_dot(axis, axis))[..., None]
    return _exp(u * angle[..., None])


def to_axis_angle(R: Rot) -> tuple[Vec3, Scalar]:
    """Unit axis and angle in ``[0, pi]`` of a rotation.

    At the identity the axis is undefined; ``e3 = (0, 0, 1)`` is returned.

    **Arguments:**

    - `R`: rotation matrix, shape `(..., 3, 3)`.

    **Returns:** ``(axis, angle)`` with shapes `(..., 3)` and `(...)`.
    """
    return _to_axis_angle(_prep(R, "R", (3, 3)))


@jax.jit
def _to_axis_angle(R: Array) -> tuple[Array, Array]:
    w = _log(R)
    t = _dot(w, w)
    zero = t == 0
    th = jnp.sqrt(jnp.where(zero, 1.0, t))
    e3 = jnp.zeros_like(w).at[..., 2].set(1.0)
    axis = jnp.where(zero[..., None], e3, w / th[..., None])
    return axis, jnp.where(zero, 0.0, th)


def _rz_ry_rx(cphi, sphi, cth, sth, cpsi, spsi) -> Array:
    return jnp.stack(
        [
            jnp.stack(
                [cphi * cth, cphi * sth * spsi - sphi * cpsi, cphi * sth * cpsi + sphi * spsi], -1
            ),
            jnp.stack(
                [sphi * cth, sphi * sth * spsi + cphi * cpsi, sphi * sth * cpsi - cphi * spsi], -1
            ),
            jnp.stack([-sth, cth * spsi, cth * cpsi], -1),
        ],
        -2,
    )


def from_euler_zyx(phi: Scalar, theta: Scalar, psi: Scalar) -> Rot:
    """Rotation from ZYX Euler angles: ``R = Rz(phi) Ry(theta) Rx(psi)``.

    (Yaw ``phi``, pitch ``theta``, roll ``psi``; intrinsic z-y'-x''.)

    **Arguments:**

    - `phi`, `theta`, `psi`: angles in radians, broadcastable shapes `(...)`.

    **Returns:** rotation matrix, shape `(..., 3, 3)`.
    """
    return _from_euler_zyx(*_prep_angles(phi, theta, psi))


def _prep_angles(phi, theta, psi) -> tuple[Array, Array, Array]:
    return tuple(_prep(a, n, ()) for a, n in ((phi, "phi"), (theta, "theta"), (psi, "psi")))


@jax.jit
def _from_euler_zyx(phi: Array, theta: Array, psi: Array) -> Array:
    phi, theta, psi = jnp.broadcast_arrays(phi, theta, psi)
    return _rz_ry_rx(
        jnp.cos(phi), jnp.sin(phi), jnp.cos(theta), jnp.sin(theta), jnp.cos(psi), jnp.sin(psi)
    )


def to_euler_zyx(R: Rot) -> tuple[Scalar, Scalar, Scalar]:
    """ZYX Euler angles ``(phi, theta, psi)`` with ``R = Rz(phi) Ry(theta) Rx(psi)``.

    Ranges: ``phi, psi`` in ``(-pi, pi]``, ``theta`` in ``[-pi/2, pi/2]``. At
    gimbal lock (``theta = +-pi/2``, see `is_gimbal_locked`) only ``phi - psi``
    (or ``phi + psi``) is determined; ``psi`` then follows from ``phi`` so that
    the returned angles still reproduce ``R`` to round-off: ``phi`` is taken
    from the first column, then ``theta`` and ``psi`` from ``Rz(phi)^T R``.

    **Arguments:**

    - `R`: rotation matrix, shape `(..., 3, 3)`.

    **Returns:** ``(phi, theta, psi)``, each of shape `(...)`.
    """
    return _to_euler_zyx(_prep(R, "R", (3, 3)))


@jax.jit
def _to_euler_zyx(R: Array) -> tuple[Array, Array, Array]:
    R00, R10, R20 = R[..., 0, 0], R[..., 1, 0], R[..., 2, 0]
    c2 = R00 * R00 + R10 * R10
    tiny = jnp.finfo(R.dtype).tiny
    locked = c2 <= tiny  # exactly at gimbal lock: phi is arbitrary, take 0
    phi = jnp.arctan2(jnp.where(locked, 0.0, R10), jnp.where(locked, 1.0, R00))
    cphi, sphi = jnp.cos(phi), jnp.sin(phi)
    # N = Rz(phi)^T R = Ry(theta) Rx(psi)
    N00 = cphi * R00 + sphi * R10
    N11 = -sphi * R[..., 0, 1] + cphi * R[..., 1, 1]
    N12 = -sphi * R[..., 0, 2] + cphi * R[..., 1, 2]
    theta = jnp.arctan2(-R20, N00)
    psi = jnp.arctan2(-N12, N11)
    return phi, theta, psi


def is_gimbal_locked(R: Rot, atol: float = 1e-6, *, seq: str = "ZYX") -> Array:
    """Whether ``R`` is within ``atol`` of gimbal lock for the Euler sequence ``seq``.

    For the default ZYX angles this is ``|cos theta| <= atol``: there
    ``det E = -cos(theta)`` vanishes (see `euler_zyx_rate_matrix`) and the Euler
    angle rates are undefined. For any ``seq`` (see `from_euler`) the test is on the
    second angle ``beta``: ``|cos beta| <= atol`` for Tait–Bryan sequences (``beta =
    +-pi/2``), ``|sin beta| <= atol`` for proper Euler ones (``beta = 0`` or ``pi``).
    There only the sum or the difference of the first and third angles is determined
    (see `to_euler`).

    **Arguments:**

    - `R`: rotation matrix, shape `(..., 3, 3)`.
    - `atol`: tolerance on ``|cos beta|`` (Tait–Bryan) or ``|sin beta|`` (proper Euler).
    - `seq`: the Euler sequence, written as for `from_euler`.

    **Returns:** boolean array, shape `(...)`.
    """
    axes, _ = _check_seq(seq)
    return _is_gimbal_locked(_prep(R, "R", (3, 3)), atol, axes)


@functools.partial(jax.jit, static_argnums=2)
def _is_gimbal_locked(R: Array, atol, axes: tuple[int, int, int]) -> Array:
    # With R = R_I(a1) R_J(beta) R_K(a3), column K of R is R_I(a1) R_J(beta) e_K: its
    # component along e_I is +-sin(beta) (Tait–Bryan) or cos(beta) (proper Euler, K = I),
    # so its other two components have the squared norm cos^2 beta or sin^2 beta.
    first, _, third = axes
    rows = [r for r in range(3) if r != first]
    return R[..., rows[0], third] ** 2 + R[..., rows[1], third] ** 2 <= atol**2


def euler_zyx_rate_matrix(phi: Scalar, theta: Scalar, psi: Scalar) -> Mat3:
    """Matrix ``E`` with body rate ``Omega = E (phi', theta', psi')``, ZYX angles.

    ``E = [[-sin th, 0, 1], [cos th sin psi, cos psi, 0], [cos th cos psi, -sin psi, 0]]``
    and ``det E = -cos(theta)``: singular at gimbal lock ``theta = +-pi/2``.

    **Arguments:**

    - `phi`, `theta`, `psi`: angles, broadcastable shapes `(...)` (``phi`` does not enter).

    **Returns:** shape `(..., 3, 3)`.
    """
    return _euler_zyx_rate_matrix(*_prep_angles(phi, theta, psi))


@jax.jit
def _euler_zyx_rate_matrix(phi: Array, theta: Array, psi: Array) -> Array:
    phi, theta, psi = jnp.broadcast_arrays(phi, theta, psi)
    cth, sth, cpsi, spsi = jnp.cos(theta), jnp.sin(theta), jnp.cos(psi), jnp.sin(psi)
    z, o = jnp.zeros_like(theta), jnp.ones_like(theta)
    return jnp.stack(
        [
            jnp.stack([-sth, z, o], -1),
            jnp.stack([cth * spsi, cpsi, z], -1),
            jnp.stack([cth * cpsi, -spsi, z], -1),
        ],
        -2,
    )


# Euler angles for any of the 24 conventions, written as SciPy's `Rotation.from_euler`
# writes them.

_EULER_SEQ_HELP = (
    "seq must be three axes from 'xyz' (extrinsic) or from 'XYZ' (intrinsic), all in one "
    "case, with no axis twice in a row (e.g. 'ZYX', 'xyz', 'ZXZ')"
)

#: Gimbal lock, exactly: `to_euler` sets the undetermined half-angle (as SciPy does) once
#: the pair of quaternion components that defines it is below this many machine epsilons
#: relative to the other pair. That changes the rebuilt rotation by about as much, so round
#: trips stay at round-off; at a lock built in floating point the ratio is about one epsilon.
_EULER_LOCK_ULPS = 8.0


def _check_seq(seq) -> tuple[tuple[int, int, int], bool]:
    """Validate an Euler sequence; return its intrinsic axes and whether it is extrinsic.

    The intrinsic axes ``(I, J, K)`` give ``R = R_I(a) R_J(b) R_K(c)`` for the angles
    in that order; an extrinsic ``seq`` 'ijk' with angles ``(a, b, c)`` is the
    intrinsic 'KJI' with angles ``(c, b, a)``.
    """
    ok = (
        isinstance(seq, str)
        and len(seq) == 3
        and (seq.isupper() or seq.islower())
        and set(seq.lower()) <= set("xyz")
        and seq[0].lower() != seq[1].lower() != seq[2].lower()
    )
    if not ok:
        raise ValueError(f"{_EULER_SEQ_HELP}; got seq={seq!r}")
    axes = tuple("xyz".index(c) for c in seq.lower())
    extrinsic = seq.islower()
    return (axes[::-1] if extrinsic else axes), extrinsic


def _axis_rotation(axis: int, c: Array, s: Array) -> Array:
    """Rotation by the angle with cosine ``c`` and sine ``s`` about the basis axis ``axis``."""
    p, q = (axis + 1) % 3, (axis + 2) % 3
    z, o = jnp.zeros_like(c), jnp.ones_like(c)
    M = [[z, z, z], [z, z, z], [z, z, z]]
    M[axis][axis] = o
    M[p][p], M[p][q] = c, -s
    M[q][p], M[q][q] = s, c
    return jnp.stack([jnp.stack(row, -1) for row in M], -2)


def from_euler(seq: str, angles: Vec3) -> Rot:
    """Rotation from Euler angles in any of the 24 conventions, as SciPy writes them.

    Uppercase ``seq`` is intrinsic (rotations about the moving axes):
    ``from_euler('ZYX', (a, b, c)) = Rz(a) Ry(b) Rx(c)``, which is
    `from_euler_zyx`. Lowercase is extrinsic (about the fixed axes):
    ``from_euler('xyz', (a, b, c)) = Rz(c) Ry(b) Rx(a)``. The 12 sequences are
    the 6 Tait–Bryan ones (three different axes, e.g. 'XYZ') and the 6 proper
    Euler ones (first axis repeated, e.g. 'ZXZ'). The same as
    ``scipy.spatial.transform.Rotation.from_euler(seq, angles).as_matrix()``.

    **Arguments:**

    - `seq`: three letters from ``xyz`` (extrinsic) or ``XYZ`` (intrinsic), no axis
      twice in a row; anything else is a ``ValueError``. A Python string: under ``jit``
      close over it (``functools.partial(from_euler, seq)``).
    - `angles`: angles in radians, in the order of ``seq``, shape `(..., 3)`.

    **Returns:** rotation matrix, shape `(..., 3, 3)`.
    """
    axes, extrinsic = _check_seq(seq)
    return _from_euler(axes, extrinsic, _prep(angles, "angles", (3,)))


@functools.partial(jax.jit, static_argnums=(0, 1))
def _from_euler(axes: tuple[int, int, int], extrinsic: bool, angles: Array) -> Array:
    if extrinsic:
        angles = angles[..., ::-1]
    c, s = jnp.cos(angles), jnp.sin(angles)
    R1, R2, R3 = (_axis_rotation(ax, c[..., n], s[..., n]) for n, ax in enumerate(axes))
    return _mm(_mm(R1, R2), R3)


def to_euler(seq: str, R: Rot) -> Vec3:
    """Euler angles of a rotation in any of the 24 conventions, as SciPy returns them.

    Inverse of `from_euler`, with SciPy's ranges: the first and third angles in
    ``[-pi, pi)``, the second in ``[-pi/2, pi/2]`` for Tait–Bryan sequences and
    ``[0, pi]`` for proper Euler ones. At gimbal lock (the second angle at
    ``+-pi/2``, respectively ``0`` or ``pi``; flag it with
    ``is_gimbal_locked(R, seq=seq)``) only the sum or the difference of the first
    and third angles is determined; then, as in
    ``scipy.spatial.transform.Rotation.as_euler`` (which also warns), the third
    angle is set to 0. Close to (but not at) gimbal lock the first and third angles
    are ill-conditioned, yet the returned angles rebuild ``R`` to round-off.

    The angles come from the quaternion of ``R`` (`to_quat`) by the direct method of
    Bernardes and Viollet: the middle angle is ``2 atan2(|(c, d)|, |(a, b)|)`` (less
    ``pi/2`` for Tait–Bryan sequences) and the half-sum and half-difference of the
    others are ``atan2(b, a)`` and ``atan2(d, c)``, with ``(a, b, c, d)`` linear in the
    quaternion. Each ``atan2`` and norm is guarded at the lock, so that values and
    gradients stay finite there (the angles are not differentiable at the lock itself).

    **Arguments:**

    - `seq`: the Euler sequence, a Python string written as for `from_euler`.
    - `R`: rotation matrix, shape `(..., 3, 3)`.

    **Returns:** angles in radians, in the order of ``seq``, shape `(..., 3)`.

    References: E. Bernardes and S. Viollet, "Quaternion to Euler angles conversion: A
    direct, general and computationally efficient method", PLoS ONE 17(11): e0276302, 2022.
    """
    axes, extrinsic = _check_seq(seq)
    return _to_euler(axes, extrinsic, _prep(R, "R", (3, 3)))


def _safe_norm(n2: Array) -> Array:
    """``sqrt(n2)`` with a finite (zero) gradient at ``n2 = 0``."""
    pos = n2 > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, n2, 1.0)), 0.0)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _to_euler(axes: tuple[int, int, int], extrinsic: bool, R: Array) -> Array:
    # Bernardes & Viollet (2022) work in the extrinsic order:
    # R = R_k(gamma) R_j(beta) R_i(alpha).
    i, j, k = axes[::-1]
    q = _to_quat(R)
    proper = i == k
    if proper:
        k = 3 - i - j
    sign = 1.0 if (j - i) % 3 == 1 else -1.0  # parity of the permutation (i, j, k)
    w, qi, qj, qk = q[..., 0], q[..., 1 + i], q[..., 1 + j], sign * q[..., 1 + k]
    # Proper Euler angles (k = the remaining axis), with c = cos(beta/2), s = sin(beta/2):
    # q = c cos(u) + c sin(u) e_i + s cos(v) e_j + sign s sin(v) e_k,
    # u = (gamma + alpha)/2, v = (gamma - alpha)/2. A Tait–Bryan sequence becomes the proper
    # (i, j, i) after a quarter turn about e_j, q -> (1 + e_j) q / sqrt(2): beta moves by
    # pi/2 and gamma is multiplied by the parity.
    if proper:
        a, b, c, d = w, qi, qj, qk
    else:
        a, b, c, d = w - qj, qi + qk, qj + w, qk - qi
    ab2, cd2 = a * a + b * b, c * c + d * d
    tol2 = (_EULER_LOCK_ULPS * jnp.finfo(R.dtype).eps) ** 2
    lock0 = cd2 <= tol2 * ab2  # middle angle 0: only the half-sum is defined
    lockpi = ab2 <= tol2 * cd2  # middle angle pi: only the half-difference is defined
    beta = 2.0 * jnp.arctan2(_safe_norm(cd2), _safe_norm(ab2))
    half_sum = jnp.arctan2(jnp.where(lockpi, 0.0, b), jnp.where(lockpi, 1.0, a))
    half_diff = jnp.arctan2(jnp.where(lock0, 0.0, d), jnp.where(lock0, 1.0, c))
    # At lock the third angle of seq is 0: gamma for extrinsic sequences, alpha for intrinsic.
    sgn = -1.0 if extrinsic else 1.0
    half_diff = jnp.where(lock0, sgn * half_sum, half_diff)
    half_sum = jnp.where(lockpi, sgn * half_diff, half_sum)
    alpha, gamma = half_sum - half_diff, half_sum + half_diff
    if not proper:
        beta = beta - 0.5 * jnp.pi
        gamma = sign * gamma
    alpha, gamma = _wrap_angle(alpha), _wrap_angle(gamma)
    out = (alpha, beta, gamma) if extrinsic else (gamma, beta, alpha)
    return jnp.stack(out, -1)


def _wrap_angle(x: Array) -> Array:
    """``x`` in ``(-3 pi, 3 pi)`` wrapped to ``[-pi, pi)`` (SciPy's range)."""
    two_pi = 2 * jnp.pi
    return jnp.where(x >= jnp.pi, x - two_pi, jnp.where(x < -jnp.pi, x + two_pi, x))


# --------------------------------------------------------------------------
# Projection, sampling, distances
# --------------------------------------------------------------------------

_POLAR_ITERS = 12


def _project(M: Array) -> Array:
    # Orthogonal polar factor by scaled Newton iteration X <- (z X + X^-T / z) / 2
    # (Higham, "Computing the polar decomposition", SIAM J. Sci. Stat. Comput. 7,
    # 1986), with the Frobenius-norm scaling z = sqrt(|X^-1| / |X|). Converges
    # quadratically; differentiable (unlike the SVD at repeated singular values).
    def cof_over_det(X):
        c0, c1, c2 = X[..., 0, :], X[..., 1, :], X[..., 2, :]
        cof = jnp.stack([_cross(c1, c2), _cross(c2, c0), _cross(c0, c1)], -2)
        return cof / _det(X)[..., None, None]  # = X^{-T}

    def body(_, X):
        Y = cof_over_det(X)
        nx = jnp.sqrt(jnp.sum(X * X, axis=(-1, -2)))
        ny = jnp.sqrt(jnp.sum(Y * Y, axis=(-1, -2)))
        z = jnp.sqrt(ny / nx)[..., None, None]
        return 0.5 * (z * X + Y / z)

    det = _det(M)
    X = jax.lax.fori_loop(
        0, _POLAR_ITERS, body, jnp.where((det > 0)[..., None, None], M, jnp.eye(3, dtype=M.dtype))
    )
    return jnp.where((det > 0)[..., None, None], X, jnp.nan)


_project_jit = jax.jit(_project)


def project(M: Mat3) -> Rot:
    """Nearest rotation to ``M`` in the Frobenius norm (orthogonal polar factor).

    Requires ``det M > 0``: a ``ValueError`` when eager, NaN under ``jit``.

    **Arguments:**

    - `M`: matrix, shape `(..., 3, 3)`.

    **Returns:** rotation matrix, shape `(..., 3, 3)`.
    """
    M = _prep(M, "M", (3, 3))
    if _is_concrete(M) and np.any(_np_det(M) <= 0):
        raise ValueError(
            "project needs det(M) > 0: a matrix with det <= 0 has no unique nearest rotation "
            "(it is a reflection or singular)"
        )
    return _project_jit(M)


def random_rotation(key, shape: tuple[int, ...] = (), dtype=None) -> Rot:
    """Rotations drawn uniformly (Haar measure) on SO(3).

    A normalised 4D Gaussian is uniform on S^3, and the double cover maps the
    uniform measure on S^3 to the Haar measure on SO(3) (Shoemake, Graphics Gems
    III, 1992).

    **Arguments:**

    - `key`: a JAX PRNG key.
    - `shape`: batch shape of the output.
    - `dtype`: float dtype (default: JAX's default float).

    **Returns:** rotation matrices, shape `shape + (3, 3)`.
    """
    if isinstance(shape, int):
        shape = (shape,)
    dtype = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    return _random_rotation(key, tuple(shape), dtype)


@functools.partial(jax.jit, static_argnums=(1, 2))
def _random_rotation(key, shape: tuple[int, ...], dtype) -> Array:
    return _from_quat(jax.random.normal(key, shape + (4,), dtype=dtype))


def geodesic_distance(R1: Rot, R2: Rot) -> Scalar:
    """Geodesic (angle) distance ``|log(R1^T R2)|`` in ``[0, pi]``.

    **Arguments:**

    - `R1`, `R2`: rotation matrices, broadcastable shapes `(..., 3, 3)`.

    **Returns:** angle in radians, shape `(...)`.
    """
    return _geodesic_distance(_prep(R1, "R1", (3, 3)), _prep(R2, "R2", (3, 3)))


@jax.jit
def _geodesic_distance(R1: Array, R2: Array) -> Array:
    q = _to_quat(_mm(_mT(R1), R2))
    n2 = _dot(q[..., 1:], q[..., 1:])
    # Test `n2 == 0` rather than `n2 > 0` so that NaN input (under jit) gives NaN, not 0.
    zero = n2 == 0
    n = jnp.sqrt(jnp.where(zero, 1.0, n2))
    return jnp.where(zero, 0.0, 2.0 * jnp.arctan2(n, q[..., 0]))


def attitude_error_function(R: Rot, Rd: Rot) -> Scalar:
    """Attitude error function ``Psi = 1/2 tr(I - Rd^T R)`` in ``[0, 2]``.

    ``Psi = 1 - cos(angle)`` of the error rotation ``Rd^T R``.

    **Arguments:**

    - `R`, `Rd`: rotation matrices, broadcastable shapes `(..., 3, 3)`.

    **Returns:** shape `(...)`.

    References: T. Lee, M. Leok, N. H. McClamroch, "Geometric tracking control
    of a quadrotor UAV on SE(3)", CDC 2010.
    """
    return _attitude_error_function(_prep(R, "R", (3, 3)), _prep(Rd, "Rd", (3, 3)))


@jax.jit
def _attitude_error_function(R: Array, Rd: Array) -> Array:
    return 0.5 * (3.0 - jnp.sum(Rd * R, axis=(-1, -2)))


def orthogonality_error(R: Rot) -> Scalar:
    """Distance from the group: ``||R^T R - I||_F``.

    **Arguments:**

    - `R`: matrix, shape `(..., 3, 3)`.

    **Returns:** shape `(...)`.
    """
    return _orthogonality_error(_prep(R, "R", (3, 3)))


@jax.jit
def _orthogonality_error(R: Array) -> Array:
    E = _mm(_mT(R), R) - jnp.eye(3, dtype=R.dtype)
    return jnp.sqrt(jnp.sum(E * E, axis=(-1, -2)))
