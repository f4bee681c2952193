"""SO(3) primitives: accuracy against independent references, identities, bad input.

References: `scipy.spatial.transform.Rotation` (exp/log, quaternions, Euler
angles, axis-angle, distances), mpmath at 40 digits (Taylor branches), NumPy's
SVD (`project`), finite differences (Jacobians, Euler rates) and
`scipy.stats` (uniformity of `random_rotation`). Gradients, float32 gradients
and batching are in `test_so3_grads.py`.
"""

import os
import subprocess
import sys
import zlib
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy import stats
from scipy.spatial.transform import Rotation

import so3jax
from so3jax import _so3, _updates

F64, F32 = np.float64, np.float32
DTYPES = [F64, F32]
# Agreement with float64 references computed from the (rounded) inputs.
ATOL = {F64: 1e-14, F32: 1e-6}
EPS = {F64: float(np.finfo(F64).eps), F32: float(np.finfo(F32).eps)}
KINDS = ["uniform", "near_identity", "near_pi"]
N = 48
mp.mp.dps = 40

PUBLIC = [
    "hat", "vee", "bracket", "adjoint", "coadjoint", "exp", "log", "left_jacobian",
    "left_jacobian_inv", "right_jacobian", "right_jacobian_inv", "from_quat", "to_quat",
    "quat_multiply", "from_axis_angle", "to_axis_angle", "from_euler_zyx", "to_euler_zyx",
    "euler_zyx_rate_matrix", "is_gimbal_locked", "project", "geodesic_distance",
    "attitude_error_function", "orthogonality_error",
]  # fmt: skip
# Jitted versions for the accuracy tests: one compilation per input shape instead of one
# per operation (eager dispatch). The eager-only behaviour (value checks) is tested below.
J = SimpleNamespace(**{name: jax.jit(getattr(so3jax, name)) for name in PUBLIC})
random_rotation = jax.jit(so3jax.random_rotation, static_argnames=("shape", "dtype"))

# --------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------


def _rng(*salt) -> np.random.Generator:
    """A generator seeded reproducibly from a test's name and parameters."""
    return np.random.default_rng([2024, *(zlib.crc32(repr(s).encode()) for s in salt)])


def unit_vectors(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def sample_rotvecs(kind, n=N, seed=0):
    """Rotation vectors drawn three ways, all with ``|w| < pi``, float64."""
    rng = np.random.default_rng([seed, KINDS.index(kind)])
    if kind == "uniform":
        return Rotation.random(n, random_state=rng).as_rotvec()
    u = unit_vectors(rng, n)
    if kind == "near_identity":
        return u * rng.uniform(0.0, 1e-7, size=(n, 1))
    if kind == "near_pi":
        return u * (np.pi - rng.uniform(0.0, 1e-9, size=(n, 1)))
    raise AssertionError(kind)


def sample_rotations(kind, n=N, seed=0):
    return Rotation.from_rotvec(sample_rotvecs(kind, n, seed)).as_matrix()


def rot_pi(u):
    """Rotation by exactly pi about the unit vector ``u``: ``2 u u^T - I``."""
    u = np.asarray(u, float)
    return 2.0 * u[..., :, None] * u[..., None, :] - np.eye(3)


def f64(x):
    return np.asarray(x, dtype=F64)


def assert_close(got, ref, atol, rtol=0.0, dtype=None):
    got = np.asarray(got)
    if dtype is not None:
        assert got.dtype == dtype, (got.dtype, dtype)
    np.testing.assert_allclose(f64(got), f64(ref), atol=atol, rtol=rtol)


def assert_close_up_to_sign(got, ref, atol):
    """Rows of ``got`` equal rows of ``ref`` or of ``-ref`` (double cover / antipodes)."""
    got, ref = f64(got), f64(ref)
    err = np.minimum(np.abs(got - ref).max(-1), np.abs(got + ref).max(-1))
    assert err.max() <= atol, err.max()


def wrap_angle(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def five_point(f, h):
    """Derivative at 0 of ``f(t)`` by the fourth-order central difference."""
    return (f(-2 * h) - 8 * f(-h) + 8 * f(h) - f(2 * h)) / (12 * h)


def np_hat(w):
    w = np.asarray(w, float)
    z = np.zeros_like(w[..., 0])
    return np.stack(
        [
            np.stack([z, -w[..., 2], w[..., 1]], -1),
            np.stack([w[..., 2], z, -w[..., 0]], -1),
            np.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def np_vee(W):
    return np.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], -1)


def np_exp(w):
    return Rotation.from_rotvec(np.asarray(w, float)).as_matrix()


def np_log(R):
    return Rotation.from_matrix(np.asarray(R, float)).as_rotvec()


# --------------------------------------------------------------------------
# Against scipy, float64 and float32
# --------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", KINDS)
def test_exp_matches_scipy(kind, dtype):
    w = sample_rotvecs(kind).astype(dtype)
    assert_close(J.exp(w), np_exp(f64(w)), ATOL[dtype], dtype=dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", KINDS)
def test_log_matches_scipy(kind, dtype):
    R = sample_rotations(kind).astype(dtype)
    got = J.log(R)
    assert got.dtype == dtype
    ref = np_log(f64(R))
    if kind == "near_pi" and dtype == F32:
        # pi - 1e-9 is not representable in float32: the rounded matrix may be a
        # rotation by just over pi, whose log is the antipodal vector.
        assert_close_up_to_sign(got, ref, ATOL[dtype])
    else:
        assert_close(got, ref, ATOL[dtype])
    assert np.all(np.linalg.norm(f64(got), axis=-1) <= np.pi * (1 + 4 * EPS[dtype]))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", KINDS)
def test_to_quat_matches_scipy(kind, dtype):
    R = sample_rotations(kind).astype(dtype)
    got = J.to_quat(R)
    assert got.dtype == dtype
    assert np.all(f64(got)[:, 0] >= 0)
    ref = Rotation.from_matrix(f64(R)).as_quat(canonical=True, scalar_first=True)
    # Near pi w ~ 1e-9 sits at the round-off level in float32: compare up to sign.
    assert_close_up_to_sign(got, ref, ATOL[dtype])
    if dtype == F64:
        assert_close(got, ref, ATOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", KINDS)
def test_from_quat_matches_scipy(kind, dtype):
    rng = _rng("from_quat", kind)
    q = Rotation.from_rotvec(sample_rotvecs(kind)).as_quat(scalar_first=True)
    # Not unit, either sign: from_quat normalises and q ~ -q.
    q = q * rng.uniform(0.2, 5.0, size=(N, 1)) * rng.choice([-1.0, 1.0], size=(N, 1))
    q = q.astype(dtype)
    ref = Rotation.from_quat(f64(q), scalar_first=True).as_matrix()
    assert_close(J.from_quat(q), ref, ATOL[dtype], dtype=dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", KINDS)
def test_from_euler_zyx_matches_scipy(kind, dtype):
    angles = Rotation.from_rotvec(sample_rotvecs(kind)).as_euler("ZYX").astype(dtype)
    got = J.from_euler_zyx(angles[:, 0], angles[:, 1], angles[:, 2])
    ref = Rotation.from_euler("ZYX", f64(angles)).as_matrix()
    assert_close(got, ref, ATOL[dtype], dtype=dtype)
    # scipy's intrinsic ZYX is Rz(phi) Ry(theta) Rx(psi):
    Rz, Ry, Rx = (
        Rotation.from_euler(ax, f64(angles[:, i : i + 1])).as_matrix() for i, ax in enumerate("zyx")
    )
    assert_close(got, Rz @ Ry @ Rx, ATOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", KINDS)
def test_to_euler_zyx_matches_scipy(kind, dtype):
    R = sample_rotations(kind).astype(dtype)
    got = np.stack([f64(a) for a in J.to_euler_zyx(R)], -1)
    ref = Rotation.from_matrix(f64(R)).as_euler("ZYX")
    # Euler angles are ill-conditioned like 1/|cos theta| near gimbal lock.
    scale = 1.0 / np.abs(np.cos(ref[:, 1:2]))
    err = np.abs(wrap_angle(got - ref)) / scale
    assert err.max() <= ATOL[dtype], err.max()
    assert np.all(np.abs(got[:, 1]) <= np.pi / 2)
    assert np.all(np.abs(got[:, [0, 2]]) <= np.pi)
    R2 = J.from_euler_zyx(*(jnp.asarray(a, dtype) for a in got.T))
    assert_close(R2, R, ATOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", KINDS)
def test_axis_angle_matches_scipy(kind, dtype):
    rng = _rng("axis_angle", kind)
    w = sample_rotvecs(kind)
    angle = np.linalg.norm(w, axis=-1)
    axis = w / angle[:, None]
    # from_axis_angle: any scale of axis, any sign/size of the angle.
    scaled = (axis * rng.uniform(0.1, 10.0, size=(N, 1))).astype(dtype)
    signed = (angle * rng.choice([-1.0, 1.0], size=N) + rng.choice([0.0, 2 * np.pi], N)).astype(
        dtype
    )
    u = f64(scaled) / np.linalg.norm(f64(scaled), axis=-1, keepdims=True)
    got = J.from_axis_angle(scaled, signed)
    assert_close(got, np_exp(u * f64(signed)[:, None]), ATOL[dtype] * 4, dtype=dtype)
    # to_axis_angle
    R = np_exp(w).astype(dtype)
    got_axis, got_angle = J.to_axis_angle(R)
    ref = np_log(f64(R))
    ref_angle = np.linalg.norm(ref, axis=-1)
    assert_close(got_angle, ref_angle, ATOL[dtype], dtype=dtype)
    assert_close(np.linalg.norm(f64(got_axis), axis=-1), 1.0, EPS[dtype] * 4)
    if kind == "near_pi":
        assert_close_up_to_sign(got_axis, ref / ref_angle[:, None], ATOL[dtype])
    else:
        # near the identity: axis error ~ eps(angle) / angle, still round-off
        assert_close(got_axis, ref / ref_angle[:, None], ATOL[dtype])


def test_to_axis_angle_identity():
    axis, angle = J.to_axis_angle(np.eye(3))
    assert_close(axis, [0.0, 0.0, 1.0], 0.0)
    assert float(angle) == 0.0


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", KINDS)
def test_distances_match_scipy(kind, dtype):
    R1 = Rotation.random(N, random_state=_rng("dist", kind))
    R2 = R1 * Rotation.from_rotvec(sample_rotvecs(kind))
    A, B = R1.as_matrix().astype(dtype), R2.as_matrix().astype(dtype)
    ref = (Rotation.from_matrix(f64(A)).inv() * Rotation.from_matrix(f64(B))).magnitude()
    assert_close(J.geodesic_distance(A, B), ref, ATOL[dtype], dtype=dtype)
    assert_close(J.geodesic_distance(B, A), ref, ATOL[dtype], dtype=dtype)
    # Psi = 1/2 tr(I - Rd^T R) = 1 - cos(angle)
    assert_close(J.attitude_error_function(B, A), 1 - np.cos(ref), ATOL[dtype], dtype=dtype)
    assert_close(J.geodesic_distance(A, A), 0.0, ATOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
def test_orthogonality_error(dtype):
    rng = _rng("orth")
    M = rng.normal(size=(N, 3, 3)).astype(dtype)
    ref = np.linalg.norm(np.swapaxes(f64(M), -1, -2) @ f64(M) - np.eye(3), axis=(-1, -2))
    assert_close(J.orthogonality_error(M), ref, 0.0, rtol=10 * EPS[dtype], dtype=dtype)
    R = sample_rotations("uniform").astype(dtype)
    assert np.all(f64(J.orthogonality_error(R)) <= 10 * EPS[dtype])


# --------------------------------------------------------------------------
# Identities (float64)
# --------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_exp_log_roundtrip(kind):
    w = sample_rotvecs(kind, seed=1)
    assert_close(J.log(J.exp(w)), w, 1e-14)
    R = sample_rotations(kind, seed=2)
    assert_close(J.exp(J.log(R)), R, 1e-14)


@pytest.mark.parametrize("u", [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0.48, -0.6, 0.64]])
def test_log_at_pi_exactly(u):
    u = np.asarray(u, float) / np.linalg.norm(u)
    R = rot_pi(u)
    w = f64(J.log(R))
    assert_close(np.linalg.norm(w), np.pi, 1e-15)
    assert_close_up_to_sign(w[None], np.pi * u[None], 1e-14)
    assert_close(J.exp(w), R, 1e-15)
    assert_close(J.to_quat(R), np.concatenate([[0.0], u]) * np.sign(w @ u), 1e-15)


def test_hat_vee():
    rng = _rng("hat")
    x, v = rng.normal(size=(2, N, 3))
    X = f64(J.hat(x))
    assert_close(X, -np.swapaxes(X, -1, -2), 0.0)
    assert_close(X @ v[..., None], np.cross(x, v)[..., None], 1e-14)
    assert_close(J.vee(X), x, 0.0)
    # vee of a general matrix is the vector of its skew part
    M = rng.normal(size=(N, 3, 3))
    assert_close(J.vee(M), np_vee(0.5 * (M - np.swapaxes(M, -1, -2))), 1e-15)
    assert J.hat(np.array([1, 2, 3])).dtype == jnp.result_type(float)


def test_bracket():
    rng = _rng("bracket")
    x, y = rng.normal(size=(2, N, 3))
    X, Y = f64(J.hat(x)), f64(J.hat(y))
    assert_close(X @ Y - Y @ X, J.hat(np.cross(x, y)), 1e-14)
    assert_close(J.bracket(x, y), np.cross(x, y), 1e-15)
    assert_close(J.hat(J.bracket(x, y)), X @ Y - Y @ X, 1e-14)


def test_adjoint_and_coadjoint():
    rng = _rng("adjoint")
    R = sample_rotations("uniform", seed=3)
    w, M = rng.normal(size=(2, N, 3))
    Rt = np.swapaxes(R, -1, -2)
    Aw = J.adjoint(R, w)
    assert_close(J.hat(Aw), R @ np_hat(w) @ Rt, 1e-14)
    assert_close(J.exp(Aw), R @ np_exp(w) @ Rt, 1e-13)  # exp(Ad_R w) = R exp(w) R^T
    # Coadjoint: dual to the adjoint under the dot-product pairing, preserves |M|.
    AM = f64(J.coadjoint(R, M))
    assert_close(AM, (R @ M[..., None])[..., 0], 1e-14)
    assert_close(np.sum(AM * f64(Aw), -1), np.sum(M * w, -1), 1e-13)
    assert_close(np.linalg.norm(AM, axis=-1), np.linalg.norm(M, axis=-1), 1e-14)


def test_rotation_preserves_cross_product():
    rng = _rng("cross")
    R = sample_rotations("uniform", seed=4)
    a, b = rng.normal(size=(2, N, 3))
    lhs = J.adjoint(R, np.cross(a, b))
    rhs = np.cross(f64(J.adjoint(R, a)), f64(J.adjoint(R, b)))
    assert_close(lhs, rhs, 1e-14)


def test_quaternion_double_cover_and_roundtrip():
    q = _rng("quat").normal(size=(N, 4))
    assert_close(J.from_quat(q), J.from_quat(-q), 1e-15)
    qn = q / np.linalg.norm(q, axis=-1, keepdims=True)
    back = f64(J.to_quat(J.from_quat(q)))
    assert_close(back, qn * np.sign(qn[:, :1]), 1e-14)


def test_quat_multiply():
    rng = _rng("qmul")
    p, q, r = rng.normal(size=(3, N, 4))
    pq = J.quat_multiply(p, q)
    assert_close(J.from_quat(pq), f64(J.from_quat(p)) @ f64(J.from_quat(q)), 1e-14)
    ref = Rotation.from_quat(p, scalar_first=True) * Rotation.from_quat(q, scalar_first=True)
    assert_close(J.from_quat(pq), ref.as_matrix(), 1e-14)
    # Hamilton product: norm multiplicative, associative, identity (1, 0, 0, 0)
    assert_close(
        np.linalg.norm(f64(pq), axis=-1),
        np.linalg.norm(p, axis=-1) * np.linalg.norm(q, axis=-1),
        0.0,
        rtol=1e-14,
    )
    lhs = J.quat_multiply(pq, r)
    rhs = J.quat_multiply(p, J.quat_multiply(q, r))
    assert_close(lhs, rhs, 1e-13)
    assert_close(J.quat_multiply(np.array([1.0, 0, 0, 0]), q), q, 0.0)
    # i j = k
    i, j, k = np.eye(4)[1:]
    assert_close(J.quat_multiply(i, j), k, 0.0)


def test_euler_rate_matrix_determinant():
    rng = _rng("det E")
    phi, theta, psi = rng.uniform(-np.pi, np.pi, size=(3, N))
    E = f64(J.euler_zyx_rate_matrix(phi, theta, psi))
    assert_close(np.linalg.det(E), -np.cos(theta), 1e-14)
    # phi does not enter
    assert_close(J.euler_zyx_rate_matrix(0.0, theta, psi), E, 0.0)


def test_euler_rate_matrix_maps_rates_to_body_velocity():
    """``hat(Omega) = R^T dR/dt`` along a path of Euler angles equals ``E @ angle rates``."""
    rng = _rng("E fd")
    a0 = rng.uniform(-1.4, 1.4, size=(N, 3))
    rate = rng.normal(size=(N, 3))
    accel = rng.normal(size=(N, 3))

    def R_of(t):  # an independent R(t): scipy, along a curved path of angles
        return Rotation.from_euler("ZYX", a0 + t * rate + t * t * accel).as_matrix()

    dR = five_point(R_of, 1e-3)
    W = np.swapaxes(R_of(0.0), -1, -2) @ dR
    assert_close(W, -np.swapaxes(W, -1, -2), 1e-10)
    E = f64(J.euler_zyx_rate_matrix(a0[:, 0], a0[:, 1], a0[:, 2]))
    assert_close((E @ rate[..., None])[..., 0], np_vee(W), 1e-10)


@pytest.mark.parametrize("theta", [np.pi / 2, -np.pi / 2])
def test_to_euler_zyx_at_gimbal_lock(theta):
    rng = _rng("gimbal", theta)
    phi, psi = rng.uniform(-np.pi, np.pi, size=(2, N))
    # (a) from from_euler_zyx (cos theta = 6e-17, not exactly 0)
    R = f64(J.from_euler_zyx(phi, theta, psi))
    assert_close(
        R,
        Rotation.from_euler("ZYX", np.stack([phi, np.full(N, theta), psi], -1)).as_matrix(),
        1e-15,
    )
    # (b) built by hand with cos theta = 0 exactly: only phi -+ psi is determined
    s = np.sign(theta)
    alpha = psi - phi if s > 0 else phi + psi
    ca, sa, z, o = np.cos(alpha), np.sin(alpha), np.zeros(N), np.ones(N)
    if s > 0:
        rows = [[z, sa, ca], [z, ca, -sa], [-o, z, z]]
    else:
        rows = [[z, -sa, -ca], [z, ca, -sa], [o, z, z]]
    R_exact = np.stack([np.stack(r, -1) for r in rows], -2)
    assert_close(R_exact, R, 1e-14)
    for M in (R, R_exact):
        angles = J.to_euler_zyx(M)
        assert_close(J.from_euler_zyx(*angles), M, 1e-12)
        assert_close(angles[1], theta, 1e-8)
        assert np.all(np.asarray(J.is_gimbal_locked(M)))
    assert np.all(np.isfinite(f64(J.to_euler_zyx(R_exact))))


def test_is_gimbal_locked_threshold():
    R = J.from_euler_zyx(0.3, np.pi / 2 - 1e-3, -0.7)  # |cos theta| = 1e-3
    assert bool(J.is_gimbal_locked(R, atol=1e-2))
    assert not bool(J.is_gimbal_locked(R, atol=1e-4))
    assert not bool(J.is_gimbal_locked(R))
    R = sample_rotations("uniform", seed=5)
    ref = np.abs(np.cos(Rotation.from_matrix(R).as_euler("ZYX")[:, 1])) <= 1e-6
    assert np.array_equal(np.asarray(J.is_gimbal_locked(R)), ref)


# --------------------------------------------------------------------------
# Jacobians against finite differences of (scipy's) exp
# --------------------------------------------------------------------------


@pytest.mark.parametrize("kind", [*KINDS, "pi_exactly"])
def test_jacobians_match_finite_differences(kind):
    rng = _rng("jac", kind)
    if kind == "pi_exactly":
        w = np.pi * unit_vectors(rng, N)
    else:
        w = sample_rotvecs(kind, seed=6)
    v = rng.normal(size=(N, 3))
    dR = five_point(lambda t: np_exp(w + t * v), 1e-3)  # d/dt exp(w + t v) at t = 0
    R = np_exp(w)
    Jr, Jl = f64(J.right_jacobian(w)), f64(J.left_jacobian(w))
    assert_close(R @ np_hat((Jr @ v[..., None])[..., 0]), dR, 1e-10)
    assert_close(np_hat((Jl @ v[..., None])[..., 0]) @ R, dR, 1e-10)
    # Inverses: J^-1 (J v) = v, both ways round, and against numpy's inverse.
    Jri, Jli = f64(J.right_jacobian_inv(w)), f64(J.left_jacobian_inv(w))
    assert_close(Jri, np.linalg.inv(Jr), 1e-12)
    assert_close(Jli, np.linalg.inv(Jl), 1e-12)
    assert_close(Jr @ Jri, np.broadcast_to(np.eye(3), Jr.shape), 1e-13)
    assert_close(Jli @ Jl, np.broadcast_to(np.eye(3), Jr.shape), 1e-13)
    # J_l(w) = J_r(-w) = exp(w) J_r(w), and J_l(w) w = w
    assert_close(Jl, J.right_jacobian(-w), 1e-15)
    assert_close(Jl, R @ Jr, 1e-13)
    assert_close((Jl @ w[..., None])[..., 0], w, 1e-14)
    # the matrix-free J_r^-1 v used by the integrators
    assert_close(jax.jit(_so3._dexpinv)(w, v), (Jri @ v[..., None])[..., 0], 1e-14)


@pytest.mark.parametrize("kind", KINDS)
def test_private_expm1_and_rmul_exp(kind):
    """``_expm1(w) = exp(w) - I`` to round-off relative to ``|w|``; ``_rmul_exp(R, w)``
    (used by the integrators) is ``R exp(w)``."""
    w = sample_rotvecs(kind, seed=10)
    W = np_hat(w)
    got = f64(jax.jit(_updates._expm1)(w))
    if kind == "near_identity":  # exp(w) - I = W + W^2/2 + O(|w|^3): exact enough at 1e-7
        err = np.abs(got - (W + W @ W / 2)).max((-1, -2)) / np.linalg.norm(w, axis=-1)
        assert err.max() <= 1e-14, err.max()
    else:
        assert_close(got, np_exp(w) - np.eye(3), 1e-14)
    R = sample_rotations("uniform", seed=11)
    assert_close(jax.jit(_updates._rmul_exp)(R, w), R @ np_exp(w), 1e-14)


@pytest.mark.parametrize("kind", KINDS)
def test_private_cayley_map_and_its_derivative(kind):
    """``_rmul_cay(R, u) = R (I - hat(u)/2)^-1 (I + hat(u)/2)`` (NumPy's solve), on the
    group; ``_dcayinv(u, v)`` inverts the body-frame derivative of ``u -> R cay(u)``
    (checked with five-point finite differences)."""
    rng = _rng("cayley", kind)
    u = sample_rotvecs(kind, seed=12)
    R = sample_rotations("uniform", seed=13)
    W, eye = np_hat(u), np.eye(3)
    cay = np.linalg.solve(eye - W / 2, eye + W / 2)
    got = f64(jax.jit(_updates._rmul_cay)(R, u))
    assert_close(got, R @ cay, 1e-14)
    assert np.abs(np.swapaxes(got, -1, -2) @ got - eye).max() <= 1e-14
    # R(t) = R cay(u + t a): body velocity v = vee(R(0)^T R'(0)); dcay^-1_u(v) = a.
    a = rng.normal(size=u.shape)

    def cay_at(t):
        Wt = np_hat(u + t * a)
        return R @ np.linalg.solve(eye - Wt / 2, eye + Wt / 2)

    dR = five_point(cay_at, 1e-3)
    Rt = R @ cay
    Vb = np.swapaxes(Rt, -1, -2) @ dR
    v = 0.5 * np.stack([Vb[..., 2, 1] - Vb[..., 1, 2], Vb[..., 0, 2] - Vb[..., 2, 0],
                        Vb[..., 1, 0] - Vb[..., 0, 1]], axis=-1)  # fmt: skip
    assert_close(f64(jax.jit(_so3._dcayinv)(u, v)), a, 1e-9)


@pytest.mark.parametrize("margin", [1e-4, 1e-2])
def test_right_jacobian_inv_near_pi_is_dlog(margin):
    """If ``R(t) = exp(u) exp(t Omega)`` then ``d/dt log R(t) = J_r^-1(u) Omega`` at 0."""
    rng = _rng("dlog", margin)
    u = unit_vectors(rng, N) * (np.pi - margin)
    Om = unit_vectors(rng, N)
    du = five_point(lambda t: np_log(np_exp(u) @ np_exp(t * Om)), 1e-6)
    got = (f64(J.right_jacobian_inv(u)) @ Om[..., None])[..., 0]
    assert_close(got, du, 1e-9)


# --------------------------------------------------------------------------
# Taylor branches against mpmath
# --------------------------------------------------------------------------


def mp_coeff(t, which):
    th = mp.sqrt(mp.mpf(float(t)))
    if which == "A":
        return mp.sin(th) / th
    if which == "B":
        return (1 - mp.cos(th)) / th**2
    if which == "C":
        return (th - mp.sin(th)) / th**3
    if which == "D":
        return (1 - (th / 2) * mp.cot(th / 2)) / th**2
    raise AssertionError(which)


def theta_sweep(dtype, cut_theta, n=60):
    """theta in [1e-9, pi] (geometric) plus the floats on both sides of a cut-off."""
    c = dtype(cut_theta)
    around = [np.nextafter(c, dtype(0)), c, np.nextafter(c, dtype(4))]
    around += list(c * (1 + np.array([-1e-3, -1e-6, 1e-6, 1e-3], dtype)))
    return np.sort(np.concatenate([np.geomspace(1e-9, np.pi, n).astype(dtype), around]))


coeffs = jax.jit(_so3._coeffs, static_argnums=1)
# Max relative error allowed against 40-digit references.
TAYLOR_RTOL = {F64: 1e-14, F32: 4e-7}


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("which", ["A", "B", "C", "D"])
def test_coeffs_match_mpmath(which, dtype):
    cut = _so3._cutoff(dtype)
    t = theta_sweep(dtype, np.sqrt(cut)) ** 2
    t = np.concatenate([t, [np.nextafter(dtype(cut), dtype(0)), dtype(cut)]]).astype(dtype)
    got = coeffs(t, which)
    assert got.dtype == dtype
    got = f64(got)
    ref = np.array([float(mp_coeff(x, which)) for x in t])
    # A = sin(th)/th vanishes at pi, where rounding th = sqrt(t) alone costs ~eps absolute.
    floor = EPS[dtype] if which == "A" else 0.0
    err = np.abs(got - ref) / (TAYLOR_RTOL[dtype] * np.abs(ref) + floor)
    assert err.max() <= 1.0, (err.max(), t[err.argmax()])
    # no jump at the cut-off beyond the accuracy of either branch
    below, at = got[-2:]
    assert abs(below - at) <= TAYLOR_RTOL[dtype] * abs(at)


@pytest.mark.parametrize("dtype", DTYPES)
def test_sincos_matches_numpy(dtype):
    """`_sincos` (range reduction and polynomials, used by the coefficient functions)
    against NumPy's float64 ``sin`` / ``cos`` of the same inputs: within an ulp of 1
    absolute up to 1e5, within a few ulp relative below 100 (float32: the three
    pieces of pi/2 leave some relative error next to the zeros of large multiples of
    pi), signs right in every quadrant, exact derivatives.

    float32 beyond |x| = 2^13 relies on XLA fusing ``k * p2`` into the subtraction (an
    FMA; its CPU backend does at the default optimisation level): without it (with
    ``--xla_backend_optimization_level=0``) the product is rounded and the error reaches
    8 ulp at 1e5, which fails here. The group updates take half-angles, far below that."""
    rng = np.random.default_rng(3)
    x = np.concatenate(
        [
            np.linspace(-20.0, 20.0, 4001),
            np.geomspace(1e-12, 1e5, 2000),
            -np.geomspace(1e-12, 1e5, 200),
            0.5 * np.pi * np.arange(-64, 65),  # the quadrant edges and the zeros
            0.25 * np.pi * np.arange(-64, 65),  # where |r| = pi/4
            rng.uniform(-100.0, 100.0, 2000),
            [0.0, -0.0],
        ]
    ).astype(dtype)
    # XLA's default level, whatever the suite's XLA_FLAGS say (JAX 0.11's emitters leave
    # the product unfused at level 0; 0.10's older ones, which the suite asks for there,
    # fuse it at any level)
    options = {"xla_backend_optimization_level": 3}
    s, c = jax.jit(_so3._sincos, compiler_options=options)(jnp.asarray(x))
    assert s.dtype == c.dtype == dtype
    xs = f64(x)
    eps = EPS[dtype]
    rel_tol = 2.0 if dtype == F64 else 4.0
    for got, ref in ((s, np.sin(xs)), (c, np.cos(xs))):
        err = np.abs(f64(got) - ref)
        assert err.max() <= eps, err.max() / eps
        small = np.abs(xs) < 100.0
        rel = err[small] / np.maximum(np.abs(ref[small]), np.finfo(F64).tiny)
        assert rel.max() <= rel_tol * eps, (rel.max() / eps, xs[small][rel.argmax()])
    # the derivative is the closed form (c dx, -s dx)
    xt = jnp.asarray(x[::50])
    ds, dc = jax.jvp(jax.vmap(_so3._sincos), (xt,), (jnp.ones_like(xt),))[1]
    np.testing.assert_array_equal(np.asarray(ds), np.asarray(_so3._sincos(xt)[1]))
    np.testing.assert_array_equal(np.asarray(dc), -np.asarray(_so3._sincos(xt)[0]))


@pytest.mark.parametrize("dtype", DTYPES)
def test_update_coeffs_match_mpmath_across_their_cutoff(dtype):
    """`_ab_coeffs` (A and B of the group updates, with a short series below a small
    cut-off) and `_abc_coeffs` (with C) against 40 digits, on both sides of their
    cut-offs and of `_cutoff`."""
    small = 1e-4 if dtype == F64 else 1e-2
    t = np.concatenate(
        [
            theta_sweep(dtype, np.sqrt(small)) ** 2,
            theta_sweep(dtype, np.sqrt(_so3._cutoff(dtype))) ** 2,
        ]
    ).astype(dtype)
    A, B = jax.jit(_so3._ab_coeffs)(t)
    assert A.dtype == B.dtype == dtype
    # the derivative rules' (A, B, C) from one sincos: A and B the same, C = (1 - A) / t
    # above `_cutoff` (its cancellation is what TAYLOR_RTOL allows for)
    A3, B3, C = jax.jit(_so3._abc_coeffs)(t)
    np.testing.assert_array_equal(np.asarray(A3), np.asarray(A))
    np.testing.assert_array_equal(np.asarray(B3), np.asarray(B))
    for which, got in (("A", A), ("B", B), ("C", C)):
        ref = np.array([float(mp_coeff(x, which)) for x in t])
        floor = EPS[dtype] if which == "A" else 0.0
        err = np.abs(f64(got) - ref) / (TAYLOR_RTOL[dtype] * np.abs(ref) + floor)
        assert err.max() <= 1.0, (which, err.max(), t[err.argmax()])


@pytest.mark.parametrize("dtype", DTYPES)
def test_exp_update_matches_mpmath(dtype):
    """``R (exp(w) - I)`` of the integrators (row cross products) against 40 digits."""
    rng = np.random.default_rng(7)
    R = Rotation.random(random_state=rng).as_matrix()
    thetas = np.concatenate([theta_sweep(dtype, 1e-2, n=12), [2.0, 3.1]])
    worst = 0.0
    Rm = mp.matrix([[mp.mpf(float(c)) for c in row] for row in R])
    for th in thetas:
        w = (SWEEP_DIRECTION * th).astype(dtype)
        x = [mp.mpf(float(c)) for c in w]
        t = mp.sqrt(sum(c * c for c in x))
        W = mp.matrix([[0, -x[2], x[1]], [x[2], 0, -x[0]], [-x[1], x[0], 0]])
        a, b = Rm * W * (mp.sin(t) / t), Rm * W * W * ((1 - mp.cos(t)) / t**2)
        ref = np.array([[float((a + b)[i, j]) for j in range(3)] for i in range(3)])
        # relative to the size of the two terms
        scale = np.array([[float(abs(a[i, j]) + abs(b[i, j])) for j in range(3)] for i in range(3)])
        got = f64(_updates._exp_increment(jnp.asarray(R, dtype), jnp.asarray(w)))
        worst = max(worst, float((np.abs(got - ref) / scale).max()))
    assert worst <= 8 * TAYLOR_RTOL[dtype], worst


def mp_jacobians(w):
    """exp and the four Jacobians of ``w`` at 40 digits, and the size of their terms."""
    w = [mp.mpf(float(x)) for x in w]
    th = mp.sqrt(sum(x * x for x in w))
    W = mp.matrix([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    W2 = W * W
    A, B, C = mp.sin(th) / th, (1 - mp.cos(th)) / th**2, (th - mp.sin(th)) / th**3
    D = (1 - (th / 2) * mp.cot(th / 2)) / th**2
    I3 = mp.eye(3)
    out = {
        "exp": ((I3, A * W, B * W2)),
        "left_jacobian": (I3, B * W, C * W2),
        "right_jacobian": (I3, -B * W, C * W2),
        "left_jacobian_inv": (I3, -W / 2, D * W2),
        "right_jacobian_inv": (I3, W / 2, D * W2),
    }

    def to_np(M):
        return np.array([[float(M[i, j]) for j in range(3)] for i in range(3)])

    return {
        k: (to_np(a + b + c), np.abs(to_np(a)) + np.abs(to_np(b)) + np.abs(to_np(c)))
        for k, (a, b, c) in out.items()
    }


SWEEP_DIRECTION = np.array([0.48, -0.6, 0.64])  # a unit vector


@pytest.mark.parametrize("dtype", DTYPES)
def test_exp_and_jacobians_match_mpmath_across_cutoff(dtype):
    thetas = theta_sweep(dtype, np.sqrt(_so3._cutoff(dtype)), n=20)
    w = (SWEEP_DIRECTION * thetas[:, None]).astype(dtype)
    refs = [mp_jacobians(x) for x in w]
    worst = {}
    for name in refs[0]:
        got = getattr(J, name)(w)
        assert got.dtype == dtype
        R = np.stack([r[name][0] for r in refs])
        size = np.stack([r[name][1] for r in refs])
        # elementwise, relative to the size of the terms that make up each entry
        worst[name] = float((np.abs(f64(got) - R) / size).max())
    assert max(worst.values()) <= 2 * TAYLOR_RTOL[dtype], worst


@pytest.mark.parametrize("dtype", DTYPES)
def test_log_matches_mpmath_across_cutoff(dtype):
    """log of ``R = exp(w)`` (at 40 digits, rounded once) returns ``w`` to round-off."""
    # log switches to the atan series at (|v| / w)^2 = tan^2(theta / 2) = _atan_cutoff
    cut_theta = 2 * np.arctan(np.sqrt(_so3._atan_cutoff(dtype)))
    thetas = theta_sweep(dtype, cut_theta, n=20)
    # (float32(pi) > pi: keep clear of the branch cut, where log is the antipode)
    thetas = thetas[f64(thetas) < np.pi - 100 * EPS[dtype]]
    w = (SWEEP_DIRECTION * thetas[:, None]).astype(dtype)
    R = np.stack([mp_jacobians(x)["exp"][0] for x in w]).astype(dtype)
    got = J.log(R)
    assert got.dtype == dtype
    err = np.abs(f64(got) - f64(w)).max(-1) / np.linalg.norm(f64(w), axis=-1)
    assert err.max() <= 2 * TAYLOR_RTOL[dtype], (err.max(), thetas[err.argmax()])


# --------------------------------------------------------------------------
# project
# --------------------------------------------------------------------------


def svd_project(M):
    U, _, Vt = np.linalg.svd(M)
    return U @ Vt


def matrices_with_singular_values(rng, sv):
    U = Rotation.random(len(sv), random_state=rng).as_matrix()
    V = Rotation.random(len(sv), random_state=rng).as_matrix()
    return U @ (sv[..., :, None] * np.swapaxes(V, -1, -2))  # det = prod(sv) > 0


@pytest.mark.parametrize("cond", [1.0, 1e3, 1e8, 1e14])
def test_project_matches_svd(cond):
    rng = _rng("project", cond)
    sv = np.stack([np.ones(N), rng.uniform(1 / cond, 1, N), np.full(N, 1 / cond)], -1)
    M = matrices_with_singular_values(rng, sv * rng.uniform(0.01, 100, (N, 1)))
    got = J.project(M)
    assert_close(got, svd_project(M), 1e-12)
    assert np.all(np.abs(np.linalg.det(f64(got)) - 1) <= 1e-14)


def test_project_random_and_near_rotations():
    rng = _rng("project2")
    M = rng.normal(size=(N, 3, 3))
    M = np.where((np.linalg.det(M) < 0)[:, None, None], -M, M)
    assert_close(J.project(M), svd_project(M), 1e-12)
    R = sample_rotations("uniform", seed=7)
    noisy = R + 1e-3 * rng.normal(size=R.shape)
    assert_close(J.project(noisy), svd_project(noisy), 1e-13)
    # idempotent on rotations
    for kind in KINDS:
        R = sample_rotations(kind, seed=8)
        assert_close(J.project(R), R, 1e-14)
        assert_close(J.project(J.project(noisy)), J.project(noisy), 1e-14)


# --------------------------------------------------------------------------
# random_rotation
# --------------------------------------------------------------------------


def test_random_rotation_is_haar():
    n = 4000
    R = f64(random_rotation(jax.random.key(0), (n,)))
    assert_close(np.linalg.det(R), 1.0, 1e-14)
    assert np.all(f64(J.orthogonality_error(R)) <= 1e-14)
    # angle density (1 - cos th) / pi on [0, pi], CDF (th - sin th) / pi
    th = np.linalg.norm(np_log(R), axis=-1)
    assert stats.kstest(th, lambda x: (x - np.sin(x)) / np.pi).pvalue > 1e-3
    # axis uniform on the sphere: each component uniform on [-1, 1]
    axis = np_log(R) / th[:, None]
    for k in range(3):
        assert stats.kstest(axis[:, k], stats.uniform(-1, 2).cdf).pvalue > 1e-3
    # E[R] = 0 and E[R_ij^2] = 1/3 (each entry has variance 1/3)
    sd = np.sqrt(1 / 3 / n)
    assert np.abs(R.mean(0)).max() <= 5 * sd
    assert np.abs((R**2).mean(0) - 1 / 3).max() <= 5 * np.sqrt(4 / 45 / n)
    # left invariance: R0 R has the same angle distribution
    R0 = np_exp([0.3, -2.0, 1.0])
    th0 = np.linalg.norm(np_log(R0 @ R), axis=-1)
    assert stats.kstest(th0, lambda x: (x - np.sin(x)) / np.pi).pvalue > 1e-3


def test_random_rotation_shape_dtype_key():
    key = jax.random.key(1)

    def out(*args, **kwargs):  # shape and dtype, traced without compiling
        return jax.eval_shape(lambda k: so3jax.random_rotation(k, *args, **kwargs), key)

    assert (out().shape, out().dtype) == ((3, 3), jnp.float64)  # x64 is on in the tests
    assert out(5).shape == (5, 3, 3)
    assert out((2, 1, 4)).shape == (2, 1, 4, 3, 3)
    assert out((2,), jnp.float32).dtype == jnp.float32
    R32 = random_rotation(key, (16,), jnp.float32)
    assert R32.dtype == jnp.float32
    # Within 32 float32 epsilons of the group: over 1000 draws the worst was 13 eps off
    # orthogonal and 9 eps off det 1 (the rounding of the normalisation and the products
    # depends on the CPU's instructions: 1e-6, about 8 eps, failed on one machine).
    eps32 = float(np.finfo(np.float32).eps)
    assert np.all(f64(J.orthogonality_error(R32)) <= 32 * eps32)
    assert_close(np.linalg.det(f64(R32)), 1.0, 32 * eps32)
    assert np.array_equal(random_rotation(key, (16,), jnp.float32), R32)  # deterministic
    other = random_rotation(jax.random.key(2), (16,), jnp.float32)
    assert not np.allclose(other, R32)
    raw = random_rotation(jax.random.PRNGKey(1), (16,), jnp.float32)  # raw uint32 keys too
    assert raw.shape == (16, 3, 3)


# --------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------

I3 = np.eye(3)
one3, one4 = np.ones(3), np.ones(4)

BAD_SHAPES = [
    (so3jax.hat, (one4,), "w", "(..., 3)"),
    (so3jax.vee, (np.ones((3, 4)),), "W", "(..., 3, 3)"),
    (so3jax.bracket, (one3, np.ones(2)), "y", "(..., 3)"),
    (so3jax.adjoint, (np.ones((3, 2)), one3), "R", "(..., 3, 3)"),
    (so3jax.adjoint, (I3, one4), "w", "(..., 3)"),
    (so3jax.coadjoint, (I3, np.ones((3, 1))), "M", "(..., 3)"),
    (so3jax.exp, (np.ones((3, 1)),), "w", "(..., 3)"),
    (so3jax.log, (one3,), "R", "(..., 3, 3)"),
    (so3jax.left_jacobian, (one4,), "w", "(..., 3)"),
    (so3jax.left_jacobian_inv, (one4,), "w", "(..., 3)"),
    (so3jax.right_jacobian, (np.float64(1.0),), "w", "(..., 3)"),
    (so3jax.right_jacobian_inv, (one4,), "w", "(..., 3)"),
    (so3jax.from_quat, (one3,), "q", "(..., 4)"),
    (so3jax.to_quat, (np.eye(4),), "R", "(..., 3, 3)"),
    (so3jax.quat_multiply, (one3, one4), "p", "(..., 4)"),
    (so3jax.quat_multiply, (one4, one3), "q", "(..., 4)"),
    (so3jax.from_axis_angle, (one4, 1.0), "axis", "(..., 3)"),
    (so3jax.to_axis_angle, (np.ones((2, 2)),), "R", "(..., 3, 3)"),
    (so3jax.to_euler_zyx, (np.ones((3, 3, 1)),), "R", "(..., 3, 3)"),
    (so3jax.is_gimbal_locked, (one3,), "R", "(..., 3, 3)"),
    (so3jax.project, (np.ones((2, 3)),), "M", "(..., 3, 3)"),
    (so3jax.geodesic_distance, (I3, one3), "R2", "(..., 3, 3)"),
    (so3jax.attitude_error_function, (one3, I3), "R", "(..., 3, 3)"),
    (so3jax.attitude_error_function, (I3, one3), "Rd", "(..., 3, 3)"),
    (so3jax.orthogonality_error, (one4,), "R", "(..., 3, 3)"),
]


@pytest.mark.parametrize(
    "fn, args, name, shape", BAD_SHAPES, ids=[f"{f.__name__}-{n}" for f, _, n, _ in BAD_SHAPES]
)
def test_wrong_trailing_shape_raises(fn, args, name, shape):
    with pytest.raises(ValueError, match=rf"^{name} must have shape \(\.\.\., [0-9, ]+\)") as e:
        fn(*args)
    assert shape in str(e.value)
    with pytest.raises(ValueError, match=rf"^{name} must have shape"):
        jax.jit(fn)(*args)  # raised while tracing


def _nan(shape, where=0, value=np.nan):
    x = np.full(shape, 0.5)
    x.reshape(-1)[where] = value
    return x


R_rand = sample_rotations("uniform", n=1, seed=9)[0]

NAN_INPUTS = [
    (so3jax.hat, lambda v: (_nan(3, value=v),), "w"),
    (so3jax.vee, lambda v: (_nan((3, 3), 1, v),), "W"),
    (so3jax.bracket, lambda v: (one3, _nan(3, 1, v)), "y"),
    (so3jax.adjoint, lambda v: (_nan((3, 3), 4, v), one3), "R"),
    (so3jax.coadjoint, lambda v: (I3, _nan(3, 2, v)), "M"),
    (so3jax.exp, lambda v: (_nan(3, value=v),), "w"),
    (so3jax.log, lambda v: (_nan((3, 3), 5, v),), "R"),
    (so3jax.left_jacobian, lambda v: (_nan(3, value=v),), "w"),
    (so3jax.left_jacobian_inv, lambda v: (_nan(3, value=v),), "w"),
    (so3jax.right_jacobian, lambda v: (_nan(3, value=v),), "w"),
    (so3jax.right_jacobian_inv, lambda v: (_nan(3, value=v),), "w"),
    (so3jax.from_quat, lambda v: (_nan(4, value=v),), "q"),
    (so3jax.to_quat, lambda v: (_nan((3, 3), 1, v),), "R"),
    (so3jax.quat_multiply, lambda v: (_nan(4, 3, v), one4), "p"),
    (so3jax.from_axis_angle, lambda v: (one3, v), "angle"),
    (so3jax.from_axis_angle, lambda v: (_nan(3, value=v), 1.0), "axis"),
    (so3jax.to_axis_angle, lambda v: (_nan((3, 3), value=v),), "R"),
    (so3jax.from_euler_zyx, lambda v: (0.1, 0.2, v), "psi"),
    (so3jax.to_euler_zyx, lambda v: (_nan((3, 3), 0, v),), "R"),
    (so3jax.euler_zyx_rate_matrix, lambda v: (0.1, v, 0.3), "theta"),
    (so3jax.project, lambda v: (_nan((3, 3), 0, v),), "M"),
    (so3jax.geodesic_distance, lambda v: (R_rand, _nan((3, 3), 3, v)), "R2"),
    (so3jax.attitude_error_function, lambda v: (_nan((3, 3), 3, v), R_rand), "R"),
    (so3jax.orthogonality_error, lambda v: (_nan((3, 3), value=v),), "R"),
]


@pytest.mark.parametrize(
    "fn, make, name", NAN_INPUTS, ids=[f"{f.__name__}-{n}" for f, _, n in NAN_INPUTS]
)
def test_non_finite_input(fn, make, name):
    for value in (np.nan, np.inf):
        with pytest.raises(ValueError, match=f"^{name} contains NaN or inf"):
            fn(*make(value))
    out = jax.jit(fn)(*make(np.nan))  # no check under jit: NaN propagates
    assert any(np.isnan(f64(o)).any() for o in jax.tree.leaves(out)), out


def test_is_gimbal_locked_nan():
    with pytest.raises(ValueError, match="^R contains NaN or inf"):
        so3jax.is_gimbal_locked(_nan((3, 3)))


def test_zero_quaternion_and_axis():
    with pytest.raises(ValueError, match="q has zero norm"):
        so3jax.from_quat(np.zeros(4))
    with pytest.raises(ValueError, match="q has zero norm"):
        so3jax.from_quat(np.stack([np.ones(4), np.zeros(4)]))  # one bad row in a batch
    assert np.isnan(f64(jax.jit(so3jax.from_quat)(np.zeros(4)))).all()
    with pytest.raises(ValueError, match="axis has zero norm"):
        so3jax.from_axis_angle(np.zeros(3), 0.5)
    assert np.isnan(f64(jax.jit(so3jax.from_axis_angle)(np.zeros(3), 0.5))).all()


@pytest.mark.parametrize(
    "M", [np.diag([1.0, 1.0, -1.0]), -np.eye(3), np.diag([1.0, 1.0, 0.0]), np.zeros((3, 3))]
)
def test_project_rejects_nonpositive_det(M):
    with pytest.raises(ValueError, match=r"det\(M\) > 0"):
        so3jax.project(M)
    with pytest.raises(ValueError, match=r"det\(M\) > 0"):
        so3jax.project(np.stack([np.eye(3), M]))
    assert np.isnan(f64(jax.jit(so3jax.project)(M))).all()
    assert np.isfinite(f64(jax.jit(so3jax.project)(np.stack([np.eye(3), M]))[0])).all()


# Concrete (non-traced) arguments for every primitive.
CONSTANT_ARGS = {
    "hat": (one3,),
    "vee": (I3,),
    "bracket": (one3, one3),
    "adjoint": (I3, one3),
    "coadjoint": (I3, one3),
    "exp": (one3,),
    "log": (I3,),
    "left_jacobian": (one3,),
    "left_jacobian_inv": (one3,),
    "right_jacobian": (one3,),
    "right_jacobian_inv": (one3,),
    "from_quat": (one4,),
    "to_quat": (I3,),
    "quat_multiply": (one4, one4),
    "from_axis_angle": (one3, 0.5),
    "to_axis_angle": (I3,),
    "from_euler_zyx": (0.1, 0.2, 0.3),
    "to_euler_zyx": (I3,),
    "euler_zyx_rate_matrix": (0.1, 0.2, 0.3),
    "is_gimbal_locked": (I3,),
    "project": (I3,),
    "geodesic_distance": (I3, I3),
    "attitude_error_function": (I3, I3),
    "orthogonality_error": (I3,),
}


@pytest.mark.parametrize("name", PUBLIC)
def test_constants_inside_traced_control_flow(name):
    """The eager value checks must not call ``bool`` on staged ops: a concrete constant
    inside a ``lax.scan`` or ``lax.cond`` body is not a tracer, but jnp ops on it are."""
    fn, args = getattr(so3jax, name), [jnp.asarray(a) for a in CONSTANT_ARGS[name]]
    assert set(CONSTANT_ARGS) == set(PUBLIC)

    def body(carry, _):
        return carry, fn(*args)

    jax.eval_shape(lambda: jax.lax.scan(body, 0.0, None, length=2))  # traces, no compile
    jax.eval_shape(lambda: jax.lax.cond(True, lambda: fn(*args), lambda: fn(*args)))


@pytest.mark.parametrize(
    "x",
    [
        8.81,
        np.float64(1.5),
        np.float32(1.5),
        np.ones(3, np.float32),
        np.eye(3),
        (0.0, 2.0),
        [0.5, 0.2, 0.1],
        [1, 2, 3],
        (1.0, 2),
        np.int64(3),
        jnp.ones(3, jnp.float32),
        True,
    ],
    ids=repr,
)
def test_as_float_matches_jnp_asarray(x):
    """NumPy and Python input skips `jnp.asarray` (a compilation per new shape), same result."""
    from so3jax._so3 import _as_float

    ref = jnp.asarray(x)
    if not jnp.issubdtype(ref.dtype, jnp.floating):
        ref = ref.astype(jnp.result_type(float))
    got = _as_float(x)
    assert isinstance(got, jax.Array)
    assert (got.dtype, got.weak_type, got.shape) == (ref.dtype, ref.weak_type, ref.shape)
    np.testing.assert_array_equal(got, ref)


def test_import_does_not_enable_x64():
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    code = "import so3jax, jax; print(jax.config.jax_enable_x64)"
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=root, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "False", out


# --------------------------------------------------------------------------
# Properties (hypothesis)
# --------------------------------------------------------------------------

_exp, _log = jax.jit(so3jax.exp), jax.jit(so3jax.log)
_from_quat, _qmul = jax.jit(so3jax.from_quat), jax.jit(so3jax.quat_multiply)

directions = st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(
    lambda v: np.linalg.norm(v) > 1e-3
)
magnitudes = st.one_of(
    st.floats(0.0, 1e-6), st.floats(0.0, np.pi - 1e-6), st.floats(np.pi - 1e-3, np.pi - 1e-6)
)
quats = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 1e-3
)


@settings(max_examples=50, deadline=None)
@given(directions, magnitudes)
def test_log_exp_property(direction, magnitude):
    w = np.asarray(direction) / np.linalg.norm(direction) * magnitude
    assert_close(_log(_exp(w)), w, 1e-12)
    assert_close(_exp(w), np_exp(w), 1e-13)


@settings(max_examples=40, deadline=None)
@given(quats, quats)
def test_composition_property(p, q):
    p, q = np.asarray(p), np.asarray(q)
    P, Q = f64(_from_quat(p)), f64(_from_quat(q))
    assert_close(_from_quat(_qmul(p, q)), P @ Q, 1e-13)
    # log of a composition agrees with scipy (away from the pi cut, where the sign is moot)
    ref = (Rotation.from_matrix(P) * Rotation.from_matrix(Q)).as_rotvec()
    got = f64(_log(P @ Q))
    if np.linalg.norm(ref) < np.pi - 1e-6:
        assert_close(got, ref, 1e-11)
    else:
        assert_close_up_to_sign(got[None], ref[None], 1e-11)
