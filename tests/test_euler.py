"""Euler angles in all 24 conventions: `from_euler`, `to_euler`, `is_gimbal_locked(seq=...)`.

References: `scipy.spatial.transform.Rotation` (`from_euler`, `as_euler`, `from_rotvec`),
central finite differences (gradients), and round trips to the rotation itself near and at
gimbal lock, where the angles are ill-conditioned but the rotation is not.
"""

import functools
import itertools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import so3jax

TAIT_BRYAN = ["".join(p) for p in itertools.permutations("xyz")]
PROPER = [a + b + a for a in "xyz" for b in "xyz" if a != b]
SEQS = [s for base in TAIT_BRYAN + PROPER for s in (base, base.upper())]
BATCH = (5, 7)


def _rng(seq, salt=0) -> np.random.Generator:
    return np.random.default_rng([7, SEQS.index(seq), salt])


def _proper(seq) -> bool:
    return seq[0].lower() == seq[2].lower()


def _wrap(x):
    return (np.asarray(x) + np.pi) % (2 * np.pi) - np.pi


def _conditioning(seq, beta):
    """``|cos beta|`` (Tait–Bryan) or ``|sin beta|`` (proper): the first and third angles
    are ill-conditioned like its inverse."""
    return np.abs(np.sin(beta) if _proper(seq) else np.cos(beta))


def _scipy_as_euler(seq, R):
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Gimbal lock", UserWarning)
        return Rotation.from_matrix(np.asarray(R, np.float64).reshape(-1, 3, 3)).as_euler(seq)


def _random_angles(seq, rng, shape=BATCH):
    angles = rng.uniform(-np.pi, np.pi, size=shape + (3,))
    if _proper(seq):
        angles[..., 1] = rng.uniform(0.0, np.pi, size=shape)
    else:
        angles[..., 1] = rng.uniform(-np.pi / 2, np.pi / 2, size=shape)
    return angles


def _lock_angles(seq, rng):
    """Angles with the second one at its singular values, 0 to 1e-9 inside the range;
    the last row 1e-3 away (not locked)."""
    angles = _random_angles(seq, rng)
    singular = [0.0, np.pi] if _proper(seq) else [-np.pi / 2, np.pi / 2]
    offsets = [0.0, 1e-15, 1e-12, 1e-9, 1e-3]
    for row, off in enumerate(offsets):
        for col in range(BATCH[1]):
            s = singular[col % 2]
            angles[row, col, 1] = s + off if s == singular[0] else s - off
    return angles, np.array(offsets)[:, None] * np.ones(BATCH)


@pytest.mark.parametrize("seq", SEQS)
def test_from_euler_matches_scipy(seq):
    angles = _random_angles(seq, _rng(seq), BATCH)
    # Angles outside SciPy's ranges are fine too.
    angles[0] += 2 * np.pi
    got = so3jax.from_euler(seq, angles)
    assert got.shape == BATCH + (3, 3)
    ref = Rotation.from_euler(seq, angles.reshape(-1, 3)).as_matrix().reshape(BATCH + (3, 3))
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-14)


@pytest.mark.parametrize("seq", SEQS)
def test_to_euler_matches_scipy_and_round_trips(seq):
    R = Rotation.random(np.prod(BATCH), random_state=_rng(seq, 1)).as_matrix()
    R = R.reshape(BATCH + (3, 3))
    got = np.asarray(so3jax.to_euler(seq, R))
    assert got.shape == BATCH + (3,)
    ref = _scipy_as_euler(seq, R).reshape(BATCH + (3,))
    # SciPy's ranges.
    assert np.all((got[..., [0, 2]] >= -np.pi) & (got[..., [0, 2]] <= np.pi))
    lo, hi = (0.0, np.pi) if _proper(seq) else (-np.pi / 2, np.pi / 2)
    assert np.all((got[..., 1] >= lo) & (got[..., 1] <= hi))
    cond = np.minimum(1.0, _conditioning(seq, ref[..., 1]))[..., None]
    err = np.abs(_wrap(got - ref)) * cond
    assert err.max() <= 1e-13, err.max()
    np.testing.assert_allclose(so3jax.from_euler(seq, got), R, rtol=0, atol=1e-14)
    locked = np.asarray(so3jax.is_gimbal_locked(R, seq=seq))
    np.testing.assert_array_equal(locked, _conditioning(seq, ref[..., 1]) <= 1e-6)


@pytest.mark.parametrize("seq", SEQS)
def test_gimbal_lock(seq):
    angles, offsets = _lock_angles(seq, _rng(seq, 2))
    R = np.asarray(so3jax.from_euler(seq, angles))
    got = np.asarray(so3jax.to_euler(seq, R))
    # The rotation is rebuilt to round-off, at and near lock.
    np.testing.assert_allclose(so3jax.from_euler(seq, got), R, rtol=0, atol=1e-14)
    locked = np.asarray(so3jax.is_gimbal_locked(R, seq=seq))
    np.testing.assert_array_equal(locked, offsets < 1e-6)
    # Exactly at lock: SciPy's choice, third angle 0 and the rest in the first.
    at = offsets == 0
    assert np.all(got[at][:, 2] == 0.0)
    ref = _scipy_as_euler(seq, R[at])
    np.testing.assert_allclose(_wrap(got[at] - ref), 0.0, atol=1e-13)
    # Away from lock the angles themselves come back.
    away = offsets == 1e-3
    np.testing.assert_allclose(_wrap(got[away] - angles[away]), 0.0, atol=1e-10)


def test_zyx_pair_is_intrinsic_zyx():
    rng = np.random.default_rng(11)
    angles = _random_angles("ZYX", rng, BATCH)
    phi, theta, psi = np.moveaxis(angles, -1, 0)
    np.testing.assert_allclose(
        so3jax.from_euler("ZYX", angles), so3jax.from_euler_zyx(phi, theta, psi), atol=1e-15
    )
    R = so3jax.from_euler_zyx(phi, theta, psi)
    old = np.stack(so3jax.to_euler_zyx(R), -1)
    np.testing.assert_allclose(_wrap(so3jax.to_euler("ZYX", R) - old), 0.0, atol=1e-13)
    # The ZYX default of is_gimbal_locked is unchanged.
    np.testing.assert_array_equal(
        so3jax.is_gimbal_locked(R, atol=0.5), so3jax.is_gimbal_locked(R, atol=0.5, seq="ZYX")
    )
    np.testing.assert_array_equal(
        so3jax.is_gimbal_locked(R, atol=0.5), np.abs(np.cos(theta)) <= 0.5
    )


FEW = ["ZYX", "xzy", "zxz"]


@pytest.mark.parametrize("seq", FEW)
def test_jit_vmap_and_float32(seq):
    rng = _rng(seq, 3)
    R64 = Rotation.random(np.prod(BATCH), random_state=rng).as_matrix().reshape(BATCH + (3, 3))
    R32 = R64.astype(np.float32)
    to_e = jax.jit(functools.partial(so3jax.to_euler, seq))
    from_e = jax.jit(functools.partial(so3jax.from_euler, seq))
    got = to_e(R32)
    assert got.dtype == jnp.float32
    ref = _scipy_as_euler(seq, R32).reshape(BATCH + (3,))
    cond = np.minimum(1.0, _conditioning(seq, ref[..., 1]))[..., None]
    assert (np.abs(_wrap(np.float64(got) - ref)) * cond).max() <= 1e-5
    back = from_e(got)
    assert back.dtype == jnp.float32
    np.testing.assert_allclose(back, R32, rtol=0, atol=1e-5)
    # vmap of the single call is the batched call.
    np.testing.assert_allclose(jax.vmap(to_e)(R32), got, rtol=0, atol=1e-6)
    angles = _random_angles(seq, rng).astype(np.float32)
    ref_R = Rotation.from_euler(seq, angles.reshape(-1, 3)).as_matrix().reshape(BATCH + (3, 3))
    np.testing.assert_allclose(from_e(angles), ref_R, rtol=0, atol=1e-5)


def _hat(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@pytest.mark.parametrize("seq", FEW)
def test_grad_to_euler_matches_finite_differences(seq):
    rng = _rng(seq, 4)
    R = Rotation.from_euler(seq, _random_angles(seq, rng, ())).as_matrix()
    c = rng.normal(size=3)
    v = rng.normal(size=3)

    def scalar(R):
        return jnp.sum(c * jnp.sin(so3jax.to_euler(seq, R)))

    grad = jax.jit(jax.grad(scalar))
    g = np.asarray(grad(R))
    assert np.all(np.isfinite(g))
    # Directional derivative along the curve R exp(t hat(v)), by SciPy's exponential.
    h = 1e-6

    def along(t):
        return float(scalar(R @ Rotation.from_rotvec(t * v).as_matrix()))

    fd = (along(h) - along(-h)) / (2 * h)
    np.testing.assert_allclose(np.sum(g * (R @ _hat(v))), fd, rtol=1e-7, atol=1e-8)
    # Finite (not NaN) at and next to gimbal lock too.
    angles, _ = _lock_angles(seq, rng)
    for a in angles[:4, :2].reshape(-1, 3):
        gl = grad(so3jax.from_euler(seq, a))
        assert np.all(np.isfinite(np.asarray(gl))), a


@pytest.mark.parametrize("seq", FEW)
def test_grad_from_euler_matches_finite_differences(seq):
    rng = _rng(seq, 5)
    a = _random_angles(seq, rng, ())
    W = rng.normal(size=(3, 3))
    g = jax.grad(lambda a: jnp.sum(W * so3jax.from_euler(seq, a)))(a)
    h = 1e-6
    fd = [
        np.sum(
            W
            * (
                Rotation.from_euler(seq, a + h * e).as_matrix()
                - Rotation.from_euler(seq, a - h * e).as_matrix()
            )
        )
        / (2 * h)
        for e in np.eye(3)
    ]
    np.testing.assert_allclose(g, fd, rtol=1e-7, atol=1e-8)


BAD = ["", "xy", "xyzx", "xYz", "Xyz", "xxy", "XYY", "zzz", "abc", "xy1", "x y", 3, None]


@pytest.mark.parametrize("seq", BAD)
def test_bad_seq_raises(seq):
    R = np.eye(3)
    for call in (
        lambda: so3jax.from_euler(seq, np.zeros(3)),
        lambda: so3jax.to_euler(seq, R),
        lambda: so3jax.is_gimbal_locked(R, seq=seq),
    ):
        with pytest.raises(ValueError, match="seq"):
            call()
