"""`SlewReference`: a rest-to-rest slew about a fixed axis, alone and in a tracking scene."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import quad
from scipy.spatial.transform import Rotation

import so3jax as s
from so3jax.plot import error_function

AXIS = np.array([1.0, 2.0, -0.5])
N = AXIS / np.linalg.norm(AXIS)
ANGLE, T = 2.0, 1.0


def profile(tau):
    """The documented degree-7 profile ``s`` and its first two derivatives in ``tau``."""
    tau = np.clip(tau, 0.0, 1.0)
    s0 = 35 * tau**4 - 84 * tau**5 + 70 * tau**6 - 20 * tau**7
    s1 = 140 * tau**3 - 420 * tau**4 + 420 * tau**5 - 140 * tau**6
    s2 = 420 * tau**2 - 1680 * tau**3 + 2100 * tau**4 - 840 * tau**5
    return s0, s1, s2


def test_rates_against_the_profile_and_derivatives():
    ref = s.SlewReference(AXIS, ANGLE, T)
    np.testing.assert_allclose(ref.axis, N, rtol=1e-15)
    ts = np.array([-0.3, 0.0, 0.1, 0.37, 0.5, 0.81, 1.0, 1.4])
    many = jax.jit(jax.vmap(lambda t: ref(t)))
    w, dw = (np.asarray(a) for a in many(ts))
    _, s1, s2 = profile(ts / T)
    np.testing.assert_allclose(w, ANGLE * (s1 / T)[:, None] * N, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(dw, ANGLE * (s2 / T**2)[:, None] * N, rtol=1e-13, atol=1e-15)
    # rest to rest: rate, acceleration and (degree 7) jerk vanish at both ends; hold outside
    ends = np.array([0.0, T, -1.0, T + 0.5])
    assert all(np.all(np.asarray(a) == 0) for a in many(ends))
    jerk = jax.jit(jax.vmap(jax.jacfwd(lambda t: ref(t)[1])))
    np.testing.assert_allclose(jerk(ends), 0.0, atol=1e-12)
    # dOmega_d is the time derivative of Omega_d: forward mode, and central differences
    # (step h = 1e-6: truncation h^2 |Omega_d'''| / 6 <= 3e-10 with |Omega_d'''| <= 840
    # angle / T^3, round-off ~ eps |Omega_d| / h ~ 1e-9)
    d_ad = jax.jit(jax.vmap(jax.jacfwd(lambda t: ref(t)[0])))(ts)
    np.testing.assert_allclose(d_ad, dw, atol=1e-12)
    h = 1e-6
    d_fd = (many(ts + h)[0] - many(ts - h)[0]) / (2 * h)
    np.testing.assert_allclose(d_fd, dw, atol=1e-8)
    # the integral of the rate over the slew is angle * axis (adaptive quadrature)
    one = jax.jit(lambda t: ref(t))
    total = [quad(lambda t, i=i: float(one(t)[0][i]), 0.0, T, epsabs=1e-13)[0] for i in range(3)]
    np.testing.assert_allclose(total, ANGLE * N, rtol=1e-12, atol=1e-13)


def test_arguments_are_checked():
    for axis in ([0.0, 0.0, 0.0], [1.0, 2.0], 1.0, [1.0, math.nan, 0.0]):
        with pytest.raises(ValueError, match="axis"):
            s.SlewReference(axis, 1.0, 1.0)
    for angle in (math.inf, math.nan, [1.0, 2.0]):
        with pytest.raises(ValueError, match="angle"):
            s.SlewReference(AXIS, angle, 1.0)
    for duration in (0.0, -1.0, math.inf, math.nan, [1.0, 2.0]):
        with pytest.raises(ValueError, match="duration"):
            s.SlewReference(AXIS, 1.0, duration)
    ref = s.SlewReference(np.asarray(AXIS, np.float32), np.float32(1.0), np.float32(2.0))
    w, dw = ref(np.float32(0.3))
    assert w.dtype == dw.dtype == jnp.float32
    np.testing.assert_allclose(w, 1.0 * profile(0.15)[1] / 2.0 * N, rtol=1e-6)


def test_vmap_and_grad_over_angle_and_duration():
    t = 0.3

    def rate(angle, duration):
        return s.SlewReference(AXIS, angle, duration)(t)[0] @ N

    angles = jnp.array([0.5, -1.0, 3.0])
    rate1 = jax.jit(rate)
    np.testing.assert_allclose(
        jax.jit(jax.vmap(rate, (0, None)))(angles, T), [rate1(a, T) for a in angles], rtol=1e-15
    )
    # d/dangle (angle s'(t)) = s'(t); d/dT by central differences
    ga, gT = jax.jit(jax.grad(rate, (0, 1)))(1.5, 0.8)
    np.testing.assert_allclose(ga, profile(t / 0.8)[1] / 0.8, rtol=1e-13)
    h = 1e-6
    np.testing.assert_allclose(gT, (rate1(1.5, 0.8 + h) - rate1(1.5, 0.8 - h)) / (2 * h), rtol=1e-8)
    # vmap of the constructor over traced axes normalises them
    axes = jnp.array([[0.0, 0.0, 2.0], [3.0, 4.0, 0.0]])
    refs = jax.vmap(lambda a: s.SlewReference(a, 1.0, 1.0))(axes)
    np.testing.assert_allclose(refs.axis, [[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]], rtol=1e-15)


def test_tracking_scene_slews_the_reference_and_the_body_follows():
    """Rd(t) = Rd0 exp(angle s(t) hat(n)); the geometric controller lands on Rd0 exp(angle n).

    For rates along a fixed axis every bracket in RKMK4 vanishes and its update of ``Rd``
    is ``exp`` of Simpson's rule for ``int Omega_d dt`` over the step. The steps end on
    ``t = T`` and composite Simpson's rule errs by ``dt^4 |f'''(T) - f'''(0)| / 2880``
    with ``f = angle s'``: ``angle (dt/T)^4 1680/2880 = 1.2e-12`` at ``dt = 1e-3``, plus
    round-off over the steps; the tolerance 1e-11 leaves a factor of about 8.
    """
    dt, n_steps = 1e-3, 2500
    Rd0 = Rotation.random(random_state=7).as_matrix()
    R0 = Rd0 @ Rotation.from_rotvec([0.4, -0.3, 0.2]).as_matrix()  # 0.54 rad off
    ref = s.SlewReference(AXIS, ANGLE, T)
    sc = s.scenes.tracking(
        s.scenes.SEED_INERTIA,
        s.GeometricGains(*s.scenes.SEED_GAINS),
        R0,
        np.array([0.2, 0.0, -0.1]),
        Rd0,
        ref,
    )
    tr = s.simulate(sc, s.RKMK4(), dt, n_steps, save_every=50)
    assert bool(tr.status.ok)
    t = np.asarray(tr.t)
    Rd = np.asarray(tr.Rd)
    target = Rd0 @ Rotation.from_rotvec(ANGLE * N).as_matrix()
    after = t >= T - 1e-12
    assert after.sum() >= 20
    err_after = np.abs(Rd[after] - target).max()
    print(f"|Rd - Rd0 exp(angle n)| after the slew: {err_after:.1e}")
    assert err_after < 1e-11
    # and during it, the closed form
    closed = Rd0 @ Rotation.from_rotvec((ANGLE * profile(t / T)[0])[:, None] * N).as_matrix()
    assert np.abs(Rd - closed).max() < 1e-11
    # the body, started 0.54 rad off with a spin, settles onto the slewed attitude
    psi = np.asarray(error_function(tr.R, tr.Rd))
    assert psi[0] > 0.05
    psi_end = float(s.attitude_error_function(tr.R[-1], jnp.asarray(target)))
    print(f"Psi at t = {t[-1]:g}: {psi_end:.1e}")
    assert psi_end < 1e-8 and psi[-1] < 1e-8
    np.testing.assert_allclose(tr.Omega[-1], 0.0, atol=1e-4)
