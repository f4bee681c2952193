"""Tests of `RigidBody` (against NumPy) and of the exact free-rigid-body solution."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from exact_rigid_body import ExactFreeBody, ambient_reference, euler_rhs, hat
from scipy.spatial.transform import Rotation

import so3jax

RNG = np.random.default_rng(1234)


def random_spd(rng, scale=1.0):
    """A physical (triangle-inequality) inertia: a rotated diagonal with moments in [1, 1.8]."""
    Q = Rotation.random(random_state=rng).as_matrix()
    return scale * Q @ np.diag(rng.uniform(1.0, 1.8, 3)) @ Q.T


# --------------------------------------------------------------------------
# RigidBody against NumPy
# --------------------------------------------------------------------------


@jax.jit
def _quantities(body, R, W, M):
    return {
        "Pi": body.body_momentum(W),
        "pi": body.spatial_momentum(R, W),
        "T": body.kinetic_energy(W),
        "C": body.casimir(W),
        "W": body.omega_from_momentum(body.body_momentum(W)),
        "free": body.euler_rhs(W),
        "forced": body.euler_rhs(W, M),
    }


@pytest.mark.parametrize("diagonal", [True, False])
@pytest.mark.parametrize("batch", [(), (5,), (2, 4)])
def test_rigid_body_quantities_match_numpy(diagonal, batch):
    rng = np.random.default_rng(7)
    moments = rng.uniform(1.0, 1.8, 3)
    J = np.diag(moments) if diagonal else random_spd(rng)
    body = so3jax.RigidBody(moments if diagonal else J)
    W = rng.normal(size=batch + (3,))
    M = rng.normal(size=batch + (3,))
    R = Rotation.random(int(np.prod(batch)), random_state=rng).as_matrix().reshape(batch + (3, 3))

    got = _quantities(body, R, W, M)

    np.testing.assert_allclose(body.inertia, J, rtol=0, atol=1e-15)
    np.testing.assert_allclose(body.inertia_inv, np.linalg.inv(J), rtol=1e-13)
    Pi = np.einsum("ij,...j->...i", J, W)
    np.testing.assert_allclose(got["Pi"], Pi, rtol=1e-13)
    pi = np.einsum("...ij,...j->...i", R, Pi)
    np.testing.assert_allclose(got["pi"], pi, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(got["T"], 0.5 * np.sum(W * Pi, -1), rtol=1e-13)
    np.testing.assert_allclose(got["C"], 0.5 * np.sum(Pi * Pi, -1), rtol=1e-13)
    np.testing.assert_allclose(got["W"], W, rtol=1e-12, atol=1e-14)
    Jinv = np.linalg.inv(J)
    free = np.einsum("ij,...j->...i", Jinv, -np.cross(W, Pi))
    forced = np.einsum("ij,...j->...i", Jinv, M - np.cross(W, Pi))
    np.testing.assert_allclose(got["free"], free, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(got["forced"], forced, rtol=1e-12, atol=1e-14)
    assert got["free"].shape == batch + (3,)
    assert got["T"].shape == batch


def test_euler_rhs_power_balance():
    """Along Euler's equations dT/dt = Omega . M and d|Pi|^2/2/dt = Pi . M (full inertia)."""
    rng = np.random.default_rng(3)
    body = so3jax.RigidBody(random_spd(rng))
    W, M = jnp.asarray(rng.normal(size=(6, 3))), jnp.asarray(rng.normal(size=(6, 3)))
    dW = body.euler_rhs(W, M)
    _, dT = jax.jvp(body.kinetic_energy, (W,), (dW,))
    _, dC = jax.jvp(body.casimir, (W,), (dW,))
    np.testing.assert_allclose(dT, jnp.sum(W * M, -1), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(dC, jnp.sum(body.body_momentum(W) * M, -1), rtol=1e-12, atol=1e-14)
    # Torque-free: both are conserved.
    _, dT0 = jax.jvp(body.kinetic_energy, (W,), (body.euler_rhs(W),))
    np.testing.assert_allclose(dT0, 0.0, atol=1e-13)


def test_rigid_body_under_jit_and_vmap():
    body = so3jax.RigidBody(jnp.array([1.0, 1.4, 1.9]))
    W = jnp.asarray(RNG.normal(size=(4, 3)))
    f = jax.jit(jax.vmap(body.euler_rhs))
    np.testing.assert_allclose(f(W), body.euler_rhs(W), rtol=1e-15, atol=1e-15)
    # A RigidBody is a pytree: it can be a jit argument.
    g = jax.jit(lambda b, w: b.kinetic_energy(w))
    np.testing.assert_allclose(g(body, W), body.kinetic_energy(W), rtol=1e-15)


def test_rigid_body_keeps_float32():
    body = so3jax.RigidBody(np.array([1.0, 2.0, 2.5], dtype=np.float32))
    W = jnp.ones(3, jnp.float32)
    assert body.inertia.dtype == jnp.float32
    assert body.euler_rhs(W).dtype == jnp.float32
    assert body.kinetic_energy(W).dtype == jnp.float32


def test_rigid_body_from_int_moments():
    body = so3jax.RigidBody([1, 2, 2])
    assert jnp.issubdtype(body.inertia.dtype, jnp.floating)
    np.testing.assert_array_equal(body.inertia, np.diag([1.0, 2.0, 2.0]))


@pytest.mark.parametrize(
    "inertia, match",
    [
        (np.array([[1.0, 0.5, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 2.5]]), "symmetric"),
        (np.diag([1.0, -1.0, 2.0]), "positive definite"),
        (np.diag([1.0, 0.0, 1.0]), "positive definite"),
        (np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "positive definite"),
        (np.eye(2), "shape"),
        (np.ones(4), "shape"),
        (np.ones((3, 3, 3)), "shape"),
        (np.array([1.0, np.nan, 2.0]), "NaN"),
    ],
)
def test_rigid_body_rejects_bad_inertia(inertia, match):
    with pytest.raises(ValueError, match=match):
        so3jax.RigidBody(inertia)


def test_rigid_body_warns_on_triangle_inequality():
    with pytest.warns(UserWarning, match="triangle"):
        so3jax.RigidBody([1.0, 1.0, 3.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        so3jax.RigidBody([1.0, 2.0, 2.5])  # physical: no warning
        so3jax.RigidBody([1.0, 1.0, 2.0])  # a thin disc, on the boundary: no warning


# --------------------------------------------------------------------------
# The exact free-body solution used as reference by the integrator tests
# --------------------------------------------------------------------------

MOMENTS = np.array([1.0, 1.5, 2.2])
R0 = Rotation.from_rotvec([0.4, -0.3, 0.9]).as_matrix()
CASES = {
    # L^2 > 2 E J2: the body tumbles around its J3 axis (dn in component 3).
    "J3-axis": np.array([0.9, -0.6, 1.3]),
    "J3-axis-negative": np.array([-0.4, 0.9, -1.2]),
    # L^2 < 2 E J2: around the J1 axis.
    "J1-axis": np.array([1.5, -0.4, 0.3]),
    "J1-axis-negative": np.array([-1.5, 0.5, 0.3]),
}

# Central difference of order 8: f'(t) = sum_k w_k f(t + k h) / h, k = -4..4.
_FD_W = np.array([1 / 280, -4 / 105, 1 / 5, -4 / 5, 0.0, 4 / 5, -1 / 5, 4 / 105, -1 / 280])


def _fd(f, t, h=0.02):
    return sum(w * f(t + k * h) for k, w in zip(range(-4, 5), _FD_W, strict=True)) / h


@pytest.mark.parametrize("case", list(CASES))
def test_exact_solution_satisfies_euler_equations(case):
    W0 = CASES[case]
    ex = ExactFreeBody(MOMENTS, R0, W0)
    assert ex.dn_axis == (2 if case.startswith("J3") else 0)
    t = np.linspace(0.0, 8.0, 33)
    W = ex.omega(t)
    np.testing.assert_allclose(ex.omega(0.0), W0, atol=1e-15)
    # Omega' = J^-1 (-Omega x J Omega), from NumPy and from the library.
    dW = _fd(ex.omega, t)
    np.testing.assert_allclose(dW, euler_rhs(MOMENTS, W), rtol=0, atol=1e-12)
    body = so3jax.RigidBody(MOMENTS)
    np.testing.assert_allclose(dW, body.euler_rhs(jnp.asarray(W)), rtol=0, atol=1e-12)
    # Energy and |Pi| are constant.
    E = 0.5 * np.sum(MOMENTS * W**2, -1)
    L = np.linalg.norm(MOMENTS * W, axis=-1)
    np.testing.assert_allclose(E, E[0], rtol=1e-14)
    np.testing.assert_allclose(L, L[0], rtol=1e-14)


@pytest.mark.parametrize("case", ["J3-axis", "J1-axis"])
def test_exact_attitude_satisfies_kinematics(case):
    W0 = CASES[case]
    ex = ExactFreeBody(MOMENTS, R0, W0)
    t = np.linspace(0.0, 6.0, 13)
    R = ex.attitude(t)
    np.testing.assert_allclose(R[0], R0, atol=1e-15)
    np.testing.assert_allclose(
        R.transpose(0, 2, 1) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-14
    )
    # R' = R hat(Omega).
    dR = _fd(ex.attitude, t)
    np.testing.assert_allclose(dR, R @ hat(ex.omega(t)), rtol=0, atol=1e-11)
    # The spatial momentum R J Omega is constant.
    pi = np.einsum("...ij,...j->...i", R, MOMENTS * ex.omega(t))
    np.testing.assert_allclose(pi, np.broadcast_to(pi[0], pi.shape), rtol=0, atol=1e-13)


@pytest.mark.parametrize("case", ["J3-axis", "J1-axis-negative"])
def test_exact_solution_matches_dop853(case):
    W0 = CASES[case]
    ex = ExactFreeBody(MOMENTS, R0, W0)
    t = np.array([0.0, 3.0, 10.0, 20.0])
    R_ref, W_ref = ambient_reference(MOMENTS, R0, W0, t)
    np.testing.assert_allclose(ex.omega(t), W_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ex.attitude(t), R_ref, rtol=0, atol=5e-12)


def test_exact_solution_rejects_bad_input():
    with pytest.raises(ValueError, match="J1 < J2 < J3"):
        ExactFreeBody([2.0, 1.0, 3.0], R0, [1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="separatrix"):
        ExactFreeBody(MOMENTS, R0, [0.0, 1.0, 0.0])


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_inverse_of_principal_moments_is_the_lu_inverse_to_the_bit(dtype):
    """``1 / J_i`` (no factorisation to compile) is what LAPACK's inverse of diag(J) gives.

    Integrators that conserve energy to round-off (LGVI) see the same ``J^-1`` either way.
    """
    rng = np.random.default_rng(5)  # physical moments (triangle inequality), scales 0.01-10
    moments = (rng.uniform(0.01, 10.0, (50, 1)) * rng.uniform(1.0, 1.8, (50, 3))).astype(dtype)
    for m in moments:
        body = so3jax.RigidBody(m)
        assert body.inertia_inv.dtype == dtype
        np.testing.assert_array_equal(body.inertia_inv, jnp.linalg.inv(jnp.diag(m)))
        np.testing.assert_array_equal(body.inertia, np.diag(m))
