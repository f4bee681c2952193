"""The geometric controller, tracking errors, controllers and references."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import so3jax as s

# ----------------------------------------------------------------------------
# An independent NumPy implementation of the formulas of Lee, Leok & McClamroch
# ----------------------------------------------------------------------------


def np_hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def np_vee(W):
    return np.array([W[2, 1], W[0, 2], W[1, 0]])


def np_torque(kR, kO, J, R, Om, Rd, Od, dOd):
    eR = 0.5 * np_vee(Rd.T @ R - R.T @ Rd)
    eO = Om - R.T @ Rd @ Od
    M = (
        -kR * eR
        - kO * eO
        + np.cross(Om, J @ Om)
        - J @ (np_hat(Om) @ R.T @ Rd @ Od - R.T @ Rd @ dOd)
    )
    return eR, eO, M


def random_inputs(rng, n):
    R = Rotation.random(n, random_state=rng).as_matrix()
    Rd = Rotation.random(n, random_state=rng).as_matrix()
    Om, Od, dOd = (rng.normal(size=(n, 3)) for _ in range(3))
    return R, Om, Rd, Od, dOd


def random_inertia(rng):
    """A physical inertia: moments (a + b, b + c, c + a) in a random principal frame."""
    a, b, c = rng.uniform(0.5, 2.0, size=3)
    Q = Rotation.random(random_state=rng).as_matrix()
    return Q @ np.diag([a + b, b + c, c + a]) @ Q.T


# Tests call the public functions through jit: one compilation instead of one per
# primitive (eager checks of the inputs are tested separately below).
torque_jit = jax.jit(s.geometric_torque)
errors_jit = jax.jit(s.tracking_errors)


@pytest.mark.parametrize("vector_gains", [False, True])
def test_geometric_torque_matches_numpy(vector_gains):
    rng = np.random.default_rng(0)
    J = random_inertia(rng)
    body = s.RigidBody(J)
    kR = rng.uniform(1, 10, size=3) if vector_gains else 8.81
    kO = rng.uniform(1, 5, size=3) if vector_gains else 2.54
    gains = s.GeometricGains(kR, kO)
    R, Om, Rd, Od, dOd = random_inputs(rng, 20)
    M = torque_jit(gains, body, R, Om, Rd, Od, dOd)  # batched
    eR, eO = errors_jit(R, Om, Rd, Od)
    for i in range(20):
        eR_ref, eO_ref, M_ref = np_torque(kR, kO, J, R[i], Om[i], Rd[i], Od[i], dOd[i])
        np.testing.assert_allclose(M[i], M_ref, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(eR[i], eR_ref, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(eO[i], eO_ref, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("vector_gains", [False, True])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_geometric_closed_loop_acceleration(vector_gains, dtype):
    """The controller's closed form of ``Omega'`` equals ``J^-1 (M - Omega x J Omega)`` of
    its torque, computed in NumPy (a full inertia tensor), and so do its derivatives."""
    rng = np.random.default_rng(11)
    J = random_inertia(rng)
    body = s.RigidBody(J.astype(dtype))
    kR = rng.uniform(1, 10, size=3) if vector_gains else 8.81
    kO = rng.uniform(1, 5, size=3) if vector_gains else 2.54
    ctrl = s.GeometricController(s.GeometricGains(np.asarray(kR, dtype), np.asarray(kO, dtype)))
    R, Om, Rd, Od, dOd = (a.astype(dtype) for a in random_inputs(rng, 20))
    acc = eqx.filter_jit(ctrl.angular_acceleration)(0.0, body, R, Om, Rd, Od, dOd)
    assert acc.dtype == dtype and acc.shape == (20, 3)
    tol = 1e-12 if dtype == np.float64 else 2e-5
    for i in range(20):
        _, _, M = np_torque(kR, kO, J, R[i], Om[i], Rd[i], Od[i], dOd[i])
        ref = np.linalg.solve(J, M - np.cross(Om[i], J @ Om[i]))
        np.testing.assert_allclose(acc[i], ref, rtol=tol, atol=tol * np.abs(ref).max())

    # Differentiated in the gains and the inertia: the same as the open form's.
    def open_form(kR, kO, Jm):
        b = s.RigidBody(Jm)
        M = s.geometric_torque(s.GeometricGains(kR, kO), b, R[0], Om[0], Rd[0], Od[0], dOd[0])
        return b.euler_rhs(Om[0], M)

    def closed(kR, kO, Jm):
        c = s.GeometricController(s.GeometricGains(kR, kO))
        return c.angular_acceleration(0.0, s.RigidBody(Jm), R[0], Om[0], Rd[0], Od[0], dOd[0])

    if dtype == np.float64:
        args = (jnp.asarray(kR, dtype), jnp.asarray(kO, dtype), jnp.asarray(J))
        d_open = jax.jit(jax.jacfwd(open_form, argnums=(0, 1, 2)))(*args)
        d_closed = jax.jit(jax.jacfwd(closed, argnums=(0, 1, 2)))(*args)
        for a, b in zip(d_closed, d_open, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10)


def test_tracking_scene_integrates_the_closed_loop():
    """`Tracking.vector_field` integrates ``J^-1 (M - Omega x J Omega)`` with its `torque`:
    the geometric and quaternion controllers' closed forms, the default for a controller
    without one or whose subclass changed its torque (saturation), and a scene subclass's
    changed torque (a disturbance) taken as it is."""
    from so3jax._state import LieState
    from so3jax._sweep_params import Disturbed

    rng = np.random.default_rng(12)
    R, Om, Rd, _, _ = random_inputs(rng, 1)
    J = random_inertia(rng)
    y = LieState(jnp.stack([R[0], Rd[0]]), jnp.asarray(Om[0]))
    t = jnp.asarray(0.7)
    seed = s.scenes.seed()
    geometric = s.scenes.tracking(
        J, s.GeometricGains(8.81, 2.54), R[0], Om[0], Rd[0], seed.reference
    )
    quat = s.scenes.tracking(J, s.QuaternionController(3.0, 1.5), R[0], Om[0], Rd[0])
    disturbed = Disturbed(
        body=geometric.body,
        controller=geometric.controller,
        reference=geometric.reference,
        y0=geometric.y0,
        disturbance=jnp.array([0.3, -0.2, 0.1]),
    )

    @jax.jit
    def parts(scene, y):
        return scene.vector_field(t, y).dx[:3], scene.torque(t, y)

    for scene, d in ((geometric, 0.0), (disturbed, disturbed.disturbance)):
        dOmega, M = parts(scene, y)
        ref = np.linalg.solve(J, np.asarray(M) - np.cross(Om[0], J @ Om[0]))
        np.testing.assert_allclose(dOmega, ref, rtol=1e-12, atol=1e-12)
        if scene is disturbed:  # the disturbance reaches the dynamics
            undisturbed = parts(geometric, y)[0]
            np.testing.assert_allclose(
                dOmega - undisturbed, np.linalg.solve(J, d), rtol=1e-10, atol=1e-12
            )

    class Damping(s.AbstractController):  # no closed form: the default path
        c: float = 0.7

        def __call__(self, t, body, R, Omega, Rd, Omega_d, dOmega_d, memory=None):
            return -self.c * Omega

    class Saturated(s.GeometricController):  # its own torque: the default path too
        def __call__(self, t, body, R, Omega, Rd, Omega_d, dOmega_d, memory=None):
            M = super().__call__(t, body, R, Omega, Rd, Omega_d, dOmega_d, memory)
            return jnp.clip(M, -0.05, 0.05)

    damped = s.scenes.tracking(J, Damping(), R[0], Om[0], Rd[0])
    saturated = s.scenes.tracking(J, Saturated(s.GeometricGains(8.81, 2.54)), R[0], Om[0], Rd[0])
    assert np.abs(parts(saturated, y)[1]).max() == pytest.approx(0.05)  # it saturates
    yq = LieState(y.R, jnp.concatenate([y.x, quat.y0.x[3:]]))
    for scene, state in ((quat, yq), (damped, y), (saturated, y)):
        dOmega, M = parts(scene, state)
        ref = np.linalg.solve(J, np.asarray(M) - np.cross(Om[0], J @ Om[0]))
        np.testing.assert_allclose(dOmega, ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(parts(damped, y)[1], -0.7 * Om[0])


def test_attitude_error_is_sin_angle_axis():
    rng = np.random.default_rng(1)
    rotvec = Rotation.random(10, random_state=rng).as_rotvec()
    Rd = Rotation.random(10, random_state=rng).as_matrix()
    R = Rd @ Rotation.from_rotvec(rotvec).as_matrix()
    eR, _ = errors_jit(R, np.zeros((10, 3)), Rd, np.zeros((10, 3)))
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    np.testing.assert_allclose(eR, np.sin(angle) * rotvec / angle, atol=1e-14)


def test_perfect_tracking_gives_zero_errors():
    rng = np.random.default_rng(2)
    J = random_inertia(rng)
    R, _, _, Od, dOd = random_inputs(rng, 8)
    Rd = R.copy()
    Om = np.einsum("nji,njk,nk->ni", R, Rd, Od)  # R^T Rd Omega_d
    eR, eO = errors_jit(R, Om, Rd, Od)
    assert np.abs(eR).max() < 1e-15
    assert np.abs(eO).max() < 1e-15
    # The torque is then the feedforward alone (the dynamics of the reference).
    M = torque_jit(s.GeometricGains(5.0, 3.0), s.RigidBody(J), R, Om, Rd, Od, dOd)
    _, _, M_ff = np_torque(0.0, 0.0, J, R[0], Om[0], Rd[0], Od[0], dOd[0])
    np.testing.assert_allclose(M[0], M_ff, atol=1e-13)


def test_jit_vmap_grad():
    rng = np.random.default_rng(3)
    body = s.RigidBody(random_inertia(rng))
    R, Om, Rd, Od, dOd = (jnp.asarray(a) for a in random_inputs(rng, 5))
    gains = s.GeometricGains(8.81, 2.54)
    M_jit = torque_jit(gains, body, R, Om, Rd, Od, dOd)
    M_vmap = jax.vmap(s.geometric_torque, in_axes=(None, None, 0, 0, 0, 0, 0))(
        gains, body, R, Om, Rd, Od, dOd
    )
    for i in range(5):
        eR_ref, eO_ref, M_ref = np_torque(
            8.81, 2.54, np.asarray(body.inertia), *(np.asarray(a[i]) for a in (R, Om, Rd, Od, dOd))
        )
        np.testing.assert_allclose(M_jit[i], M_ref, atol=1e-12)
        np.testing.assert_allclose(M_vmap[i], M_ref, atol=1e-12)

    # vmap over the gains themselves (how a sweep batches them).
    kRs = jnp.array([1.0, 4.0, 9.0])
    batched = jax.vmap(s.GeometricGains, in_axes=(0, None))(kRs, 2.0)
    Ms = jax.vmap(lambda g: s.geometric_torque(g, body, R[0], Om[0], Rd[0], Od[0], dOd[0]))(batched)
    for k, M in zip(kRs, Ms, strict=True):
        g = s.GeometricGains(k, 2.0)
        np.testing.assert_allclose(
            M, torque_jit(g, body, R[0], Om[0], Rd[0], Od[0], dOd[0]), atol=1e-13
        )

    # grad with respect to the gains: M is linear in them, dM/dk_R = -e_R.
    w = jnp.array([0.3, -1.0, 2.0])

    def cost(g):
        return jnp.dot(w, s.geometric_torque(g, body, R[0], Om[0], Rd[0], Od[0], dOd[0]))

    grads = jax.jit(jax.grad(cost))(gains)
    eR, eO = errors_jit(R[0], Om[0], Rd[0], Od[0])
    np.testing.assert_allclose(grads.k_R, -jnp.dot(w, eR), rtol=1e-12)
    np.testing.assert_allclose(grads.k_Omega, -jnp.dot(w, eO), rtol=1e-12)

    # grad with respect to the attitude, against central finite differences along exp.
    @jax.jit
    def cost_R(xi):
        Rp = R[0] @ s.exp(xi)
        return jnp.dot(w, s.geometric_torque(gains, body, Rp, Om[0], Rd[0], Od[0], dOd[0]))

    g = jax.jit(jax.grad(cost_R))(jnp.zeros(3))
    h = 1e-6
    E = h * jnp.eye(3)
    fd = (jax.vmap(cost_R)(E) - jax.vmap(cost_R)(-E)) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-7, atol=1e-8)


@pytest.mark.parametrize(
    "kR, kO, match",
    [
        (-1.0, 1.0, "k_R must be non-negative"),
        (1.0, -0.1, "k_Omega must be non-negative"),
        (np.nan, 1.0, "k_R must be finite"),
        (1.0, np.inf, "k_Omega must be finite"),
        (np.ones(2), 1.0, "k_R must be a scalar or a 3-vector"),
        (np.ones((3, 3)), 1.0, "k_R must be a scalar or a 3-vector"),
        ([1.0, -2.0, 3.0], 1.0, "k_R must be non-negative"),
    ],
)
def test_bad_gains_raise(kR, kO, match):
    with pytest.raises(ValueError, match=match):
        s.GeometricGains(kR, kO)


def test_bad_arguments_raise():
    body = s.RigidBody(jnp.ones(3))
    I, z = jnp.eye(3), jnp.zeros(3)
    with pytest.raises(TypeError, match="gains must be a GeometricGains"):
        s.geometric_torque((1.0, 2.0), body, I, z, I, z, z)
    with pytest.raises(TypeError, match="body must be a RigidBody"):
        s.geometric_torque(s.GeometricGains(1.0, 1.0), jnp.eye(3), I, z, I, z, z)
    with pytest.raises(ValueError, match=r"Omega_d must have shape \(\.\.\., 3\)"):
        s.tracking_errors(I, z, I, jnp.zeros(4))
    with pytest.raises(ValueError, match="R contains NaN"):
        s.tracking_errors(jnp.full((3, 3), jnp.nan), z, I, z)
    with pytest.raises(ValueError, match="delta must be in"):
        s.QuaternionController(1.0, 1.0, delta=1.5)


# ----------------------------------------------------------------------------
# The quaternion controller
# ----------------------------------------------------------------------------


def test_quaternion_controller_torque_and_memory():
    rng = np.random.default_rng(4)
    J = random_inertia(rng)
    body = s.RigidBody(J)
    R, Om, Rd, Od, dOd = random_inputs(rng, 1)
    R, Om, Rd, Od, dOd = R[0], Om[0], Rd[0], Od[0], dOd[0]
    kq, kO = 3.0, 1.5
    ctrl = s.QuaternionController(kq, kO, delta=0.1)
    mem = eqx.filter_jit(ctrl.init_memory)(R, Rd)
    call = eqx.filter_jit(ctrl.__call__)
    # The error quaternion of Rd^T R (scipy is scalar-last), with eta >= 0.
    q = Rotation.from_matrix(Rd.T @ R).as_quat()
    q = np.concatenate([q[3:], q[:3]])
    q = q if q[0] >= 0 else -q
    np.testing.assert_allclose(mem, np.concatenate([[1.0], q]), atol=1e-14)
    _, _, M_ff = np_torque(0.0, kO, J, R, Om, Rd, Od, dOd)  # -k_Omega e_Omega + feedforward
    M = call(0.0, body, R, Om, Rd, Od, dOd, mem)
    np.testing.assert_allclose(M, M_ff - kq * q[1:], atol=1e-12)
    # h = -1 flips the attitude feedback.
    mem_neg = mem.at[0].set(-1.0)
    np.testing.assert_allclose(call(0.0, body, R, Om, Rd, Od, dOd, mem_neg), M_ff + kq * q[1:])
    # The lift is continuous: a stored lift near -q keeps -q.
    mem_lift = jnp.concatenate([jnp.ones(1), -jnp.asarray(q)])
    np.testing.assert_allclose(
        eqx.filter_jit(ctrl.update_memory)(R, Rd, mem_lift)[1:], -q, atol=1e-14
    )


def test_quaternion_hysteresis_logic():
    # Error of 3 rad about e3, lifted with eta < -delta when h = 1: a jump to h = -1.
    R = np.asarray(s.exp(jnp.array([0.0, 0.0, 3.0])))
    I = np.eye(3)
    q = np.array([np.cos(1.5), 0.0, 0.0, np.sin(1.5)])  # eta = 0.07
    for hysteresis, delta, lift_sign, h_after in [
        (True, 0.05, -1, -1.0),  # h eta = -0.07 < -0.05: flip
        (True, 0.1, -1, 1.0),  # within the hysteresis band: keep
        (True, 0.05, 1, 1.0),  # h eta > 0: keep
        (False, 0.0, -1, 1.0),  # no hysteresis: h stays 1 (the unwinding controller)
    ]:
        ctrl = s.QuaternionController(1.0, 1.0, delta=delta, hysteresis=hysteresis)
        mem = jnp.concatenate([jnp.ones(1), lift_sign * jnp.asarray(q)])
        new = eqx.filter_jit(ctrl.update_memory)(R, I, mem)
        assert float(new[0]) == h_after
        np.testing.assert_allclose(new[1:], lift_sign * q, atol=1e-14)


# ----------------------------------------------------------------------------
# References
# ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "ref",
    [
        s.ConstantRate(jnp.array([0.1, -0.2, 0.3])),
        s.SinusoidalRate(),
        s.SinusoidalRate(jnp.array([0.1, 0.2, 0.3]), 0.7, 0.4),
        s.ConingRate(1.0, 0.5, 2.0),
    ],
)
def test_reference_derivative(ref):
    ts = jnp.linspace(0.0, 7.0, 11)
    f = jax.jit(jax.vmap(ref))
    w, dw = f(ts)
    assert w.shape == dw.shape == (11, 3)
    d_ad = jax.jit(jax.vmap(jax.jacfwd(lambda t: ref(t)[0])))(ts)
    np.testing.assert_allclose(dw, d_ad, atol=1e-13)
    # and against central differences of the rate
    h = 1e-5
    fd = (f(ts + h)[0] - f(ts - h)[0]) / (2 * h)
    np.testing.assert_allclose(dw, fd, atol=1e-8)


def test_seed_reference_profile_and_traceable_parameters():
    ref = s.SinusoidalRate()
    t = 1.3
    expected = 0.5 * np.sin(2 * np.pi * 0.2 * t + np.array([0, 2 * np.pi / 3, 4 * np.pi / 3]))
    np.testing.assert_allclose(ref(t)[0], expected, atol=1e-15)
    # grad with respect to the reference parameters
    w = jnp.array([1.0, 2.0, 3.0])
    g = jax.grad(lambda r: jnp.dot(w, r(t)[0]))(ref)
    np.testing.assert_allclose(g.amplitude, jnp.dot(w, expected / 0.5), atol=1e-14)
    assert eqx.is_array(g.frequency)
    with pytest.raises(ValueError, match="amplitude must be a scalar or a 3-vector"):
        s.SinusoidalRate(amplitude=jnp.ones(4))
    with pytest.raises(ValueError, match="rate must be a 3-vector"):
        s.ConstantRate(1.0)
