"""Actuator limits, sampled-and-held control and a disturbance in the tracking scenes.

The reference is an independent NumPy/SciPy model of the seed scene: Euler's
equations and ``R' = R hat(Omega)``, ``Rd' = Rd hat(Omega_d(t))`` in R^9 x R^3 x R^9,
with the geometric controller's torque written from its formula (Lee, Leok &
McClamroch, CDC 2010), clipped per axis, held over each control period and disturbed.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import so3jax as s
from so3jax._trajectory import NONFINITE_PARAMETER, OK
from so3jax._tune import with_gains

J = np.diag(s.scenes.SEED_INERTIA)
KR, KO = s.scenes.SEED_GAINS
SEED = s.scenes.seed()
#: The seed's arguments to `scenes.tracking`, from its scene.
ARGS = (SEED.body, SEED.controller, SEED.y0.R[0], SEED.y0.x[:3], SEED.y0.R[1], SEED.reference)
#: Per-axis limit (N m): the seed's first torque is about (-5.1, 2.2, -8.3).
MAX_TORQUE = np.array([2.0, 1.5, 2.5])
DISTURBANCE = np.array([0.05, -0.03, 0.02])
PERIOD, STEPS = 0.05, 10  # control period and RKMK4 steps per period
N_HOLDS = 40  # 2 s


def hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def vee(W):
    return np.array([W[2, 1], W[0, 2], W[1, 0]])


def reference(t):
    """The seed profile (`SinusoidalRate()`): 0.5 sin(2 pi 0.2 t + phi_i)."""
    w, phi = 2 * np.pi * 0.2, np.array([0.0, 2 * np.pi / 3, 4 * np.pi / 3])
    return 0.5 * np.sin(w * t + phi), 0.5 * w * np.cos(w * t + phi)


def geometric_torque(t, R, Om, Rd, kR=KR, kO=KO):
    """``-k_R e_R - k_Omega e_Omega + Omega x J Omega - J (hat(Omega) R^T Rd Od - R^T Rd dOd)``."""
    Od, dOd = reference(t)
    eR = 0.5 * vee(Rd.T @ R - R.T @ Rd)
    eO = Om - R.T @ Rd @ Od
    return (
        -kR * eR - kO * eO + np.cross(Om, J @ Om) - J @ (hat(Om) @ R.T @ Rd @ Od - R.T @ Rd @ dOd)
    )


def rhs(t, y, torque):
    """Euler's equations under the body torque ``torque(t, R, Om, Rd)``; both attitudes."""
    R, Om, Rd = y[:9].reshape(3, 3), y[9:12], y[12:].reshape(3, 3)
    Od, _ = reference(t)
    dOm = np.linalg.solve(J, torque(t, R, Om, Rd) - np.cross(Om, J @ Om))
    return np.concatenate([(R @ hat(Om)).ravel(), dOm, (Rd @ hat(Od)).ravel()])


def y_start():
    return np.concatenate([np.ravel(SEED.y0.R[0]), np.zeros(3), np.eye(3).ravel()])


def split(y):
    return y[:9].reshape(3, 3), y[9:12], y[12:].reshape(3, 3)


@functools.cache
def sampled_reference():
    """States and commanded torques at the sample times ``k T``: SciPy per hold interval
    (the torque is constant there, so the ODE is smooth on each)."""
    y = y_start()
    ys, cmds = [y], []
    for k in range(N_HOLDS):
        t = k * PERIOD
        M_cmd = geometric_torque(t, *split(y))
        M = np.clip(M_cmd, -MAX_TORQUE, MAX_TORQUE) + DISTURBANCE
        sol = solve_ivp(
            rhs, (t, t + PERIOD), y, "DOP853", rtol=1e-12, atol=1e-12, args=(lambda *a: M,)
        )
        assert sol.success
        y = sol.y[:, -1]
        ys.append(y)
        cmds.append(M_cmd)
    cmds.append(geometric_torque(N_HOLDS * PERIOD, *split(y)))
    return np.stack(ys), np.stack(cmds)


def test_sampled_clipped_disturbed_seed_matches_scipy():
    """All three options on the seed against SciPy, at every sample time (RKMK4, 10 steps
    per period: the held torque is constant over each step, so RKMK4's error is its
    smooth-ODE one); in between, the command is held."""
    scene = s.scenes.tracking(
        *ARGS, max_torque=MAX_TORQUE, control_period=PERIOD, disturbance=DISTURBANCE
    )
    every = s.simulate(scene, s.RKMK4(), PERIOD / STEPS, N_HOLDS * STEPS)
    assert bool(every.status.ok)
    # The command is held: it changes only at multiples of the period.
    changes = np.flatnonzero(np.any(np.diff(every.extras["M_cmd"], axis=0) != 0, axis=-1)) + 1
    np.testing.assert_array_equal(changes, STEPS * np.arange(1, N_HOLDS + 1))
    ys, cmds = sampled_reference()
    at = slice(None, None, STEPS)  # the sample times
    np.testing.assert_allclose(every.t[at], PERIOD * np.arange(N_HOLDS + 1), atol=1e-13)
    np.testing.assert_allclose(every.R[at], ys[:, :9].reshape(-1, 3, 3), atol=1e-8)
    np.testing.assert_allclose(every.Omega[at], ys[:, 9:12], atol=1e-8)
    np.testing.assert_allclose(every.Rd[at], ys[:, 12:].reshape(-1, 3, 3), atol=1e-8)
    np.testing.assert_allclose(every.extras["M_cmd"][at], cmds, atol=1e-7)
    # The saved M is the applied torque: the command clipped, without the disturbance.
    np.testing.assert_allclose(every.M[at], np.clip(cmds, -MAX_TORQUE, MAX_TORQUE), atol=1e-7)
    # The clip saturates for part of the run, and not for all of it.
    saturated = np.any(np.abs(cmds) > MAX_TORQUE, axis=-1)
    assert 2 <= saturated.sum() <= N_HOLDS - 10


def test_continuous_clip_matches_scipy():
    """``max_torque`` alone: the clipped torque evaluated continuously. The vector field is
    only piecewise smooth (a kink where a component meets the limit): across a kink
    RKMK4 loses its order (about second order here, 1e-6 at dt = 1e-3), so the
    tolerance is looser than for the sampled scene."""
    scene = s.scenes.tracking(*ARGS, max_torque=MAX_TORQUE)
    tr = s.simulate(scene, s.RKMK4(), 1e-3, 1000, save_every=250)

    def torque(t, R, Om, Rd):
        return np.clip(geometric_torque(t, R, Om, Rd), -MAX_TORQUE, MAX_TORQUE)

    sol = solve_ivp(
        rhs,
        (0.0, 1.0),
        y_start(),
        "DOP853",
        rtol=1e-12,
        atol=1e-12,
        args=(torque,),
        t_eval=[0.0, 0.25, 0.5, 0.75, 1.0],
    )
    ys = sol.y.T
    np.testing.assert_allclose(tr.R, ys[:, :9].reshape(-1, 3, 3), atol=5e-6)
    np.testing.assert_allclose(tr.Omega, ys[:, 9:12], atol=5e-6)
    cmd = np.stack([geometric_torque(t, *split(y)) for t, y in zip(sol.t, ys, strict=True)])
    np.testing.assert_allclose(tr.extras["M_cmd"], cmd, atol=1e-5)
    np.testing.assert_allclose(tr.M, np.clip(cmd, -MAX_TORQUE, MAX_TORQUE), atol=1e-5)
    assert np.any(np.abs(cmd[0]) > MAX_TORQUE)


def test_without_options_the_scene_and_program_are_unchanged():
    """All three options ``None``: the same leaves, the same jaxpr, the same numbers."""
    plain = s.scenes.tracking(*ARGS)
    none = s.scenes.tracking(*ARGS, max_torque=None, control_period=None, disturbance=None)
    assert type(none) is type(plain) is s.scenes.Tracking
    assert jax.tree.structure(none) == jax.tree.structure(plain)

    def run(scene):
        return s.simulate(scene, s.RKMK4(), 0.01, 30)

    assert str(jax.make_jaxpr(run)(none)) == str(jax.make_jaxpr(run)(plain))
    a, b = run(plain), run(none)
    assert "M_cmd" not in b.extras
    for u, v in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(u, v)


def test_gain_gradient_through_the_limit():
    """d cost / d k_R through the clip (reverse mode, what a tuner uses): central
    differences where the limit is never met (50 N m); finite where it saturates
    (2 N m), and there the limit's own derivative too. LieEuler keeps the compilation
    short; the derivative is that of the discrete map, whatever the method."""
    limited = s.scenes.tracking(*ARGS, max_torque=1.0)

    def run(k_R, max_torque):
        scene = eqx.tree_at(lambda sc: sc.max_torque, limited, max_torque)
        tr = s.simulate(with_gains(scene, k_R, KO), s.LieEuler(), 0.01, 60)
        cost = jnp.sum(tr.extras["e_R"][-1] ** 2) + jnp.sum(tr.Omega[-1] ** 2)
        return cost, jnp.max(jnp.abs(tr.extras["M_cmd"]))

    f = jax.jit(jax.value_and_grad(run, argnums=(0, 1), has_aux=True))
    h = 1e-5
    (lo, _), _ = f(jnp.asarray(KR - h), jnp.asarray(50.0))
    (hi, _), _ = f(jnp.asarray(KR + h), jnp.asarray(50.0))
    (_, peak), (d_gain, d_max) = f(jnp.asarray(KR), jnp.asarray(50.0))
    assert float(peak) < 50.0  # the limit is never met ...
    np.testing.assert_allclose(d_gain, (hi - lo) / (2 * h), rtol=1e-6)
    assert float(d_max) == 0.0  # ... so it does not matter
    (_, peak), (d_gain, d_max) = f(jnp.asarray(KR), jnp.asarray(2.0))
    assert float(peak) > 2.0  # saturating
    assert np.isfinite(float(d_gain)) and np.isfinite(float(d_max)) and float(d_max) != 0.0


def test_with_inertia_and_with_gains_keep_the_options():
    scene = s.scenes.tracking(
        *ARGS, max_torque=MAX_TORQUE, control_period=PERIOD, disturbance=DISTURBANCE
    )
    other = scene.with_inertia(s.RigidBody(2 * J))
    assert type(other) is type(scene)
    np.testing.assert_array_equal(other.max_torque, MAX_TORQUE)
    np.testing.assert_array_equal(other.control_period, PERIOD)
    np.testing.assert_array_equal(other.disturbance, DISTURBANCE)
    # The held first sample is recomputed for the new body (feedforward Omega x J Omega = 0
    # at rest, so only J dOmega_d changes it).
    M0 = geometric_torque(0.0, *split(y_start()))
    np.testing.assert_allclose(scene.y0.x[3:6], M0, atol=1e-12)
    assert float(jnp.max(jnp.abs(other.y0.x[3:6] - scene.y0.x[3:6]))) > 0
    # Gains swapped, or another start: the first sample is taken anew before stepping.
    swapped = with_gains(scene, 4.0, KO).for_step(PERIOD / STEPS, 0.0)
    np.testing.assert_allclose(
        swapped.y0.x[3:6], geometric_torque(0.0, *split(y_start()), kR=4.0), atol=1e-12
    )
    R1 = np.asarray(s.exp(np.array([0.3, -0.2, 0.1])))
    moved = scene.restarted(R1).for_step(PERIOD / STEPS, 0.0)
    np.testing.assert_array_equal(moved.y0.R[0], R1)
    np.testing.assert_allclose(
        moved.y0.x[3:6], geometric_torque(0.0, R1, np.zeros(3), np.eye(3)), atol=1e-12
    )


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(max_torque=0.0), "max_torque"),
        (dict(max_torque=[1.0, -1.0, 1.0]), "max_torque"),
        (dict(max_torque=[1.0, 1.0]), "max_torque"),
        (dict(max_torque=np.nan), "max_torque"),
        (dict(control_period=0.0), "control_period"),
        (dict(control_period=-0.01), "control_period"),
        (dict(control_period=[0.01, 0.02]), "control_period"),
        (dict(disturbance=[0.1, 0.2]), "disturbance"),
        (dict(disturbance=0.1), "disturbance"),
        (dict(disturbance=[0.0, np.inf, 0.0]), "disturbance"),
    ],
)
def test_bad_options_name_the_argument(kwargs, name):
    with pytest.raises(ValueError, match=name):
        s.scenes.tracking(*ARGS, **kwargs)


def test_sampled_scene_needs_steps_that_divide_the_period():
    scene = s.scenes.tracking(*ARGS, control_period=PERIOD)
    with pytest.raises(ValueError, match="control_period"):
        s.simulate(scene, s.RKMK4(), 0.03, 10)
    with pytest.raises(ValueError, match="control_period"):
        s.simulate(scene, s.RKMK45(), t1=1.0, rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="control_period"):  # checked before compiling
        s.sweep(scene, [1.0], [1.0], n_attitudes=2, dt=0.03, n_steps=10)


def test_traced_options_are_checked_for_shape_only():
    """Under ``jit`` the values are tracers: shapes raise, a non-finite value marks its run
    (`Status`), the other runs of the batch go on untouched."""

    def run(max_torque):
        scene = s.scenes.tracking(*ARGS, max_torque=max_torque, disturbance=DISTURBANCE)
        return s.simulate(scene, s.RKMK4(), 0.01, 5, scalarize=False)

    batch = jax.jit(jax.vmap(run))(jnp.stack([jnp.asarray(MAX_TORQUE), jnp.full(3, jnp.nan)]))
    assert int(batch.status.code[0]) == OK
    assert int(batch.status.code[1]) == NONFINITE_PARAMETER
    np.testing.assert_allclose(batch.M[0, 0], -MAX_TORQUE * [1, -1, 1])  # clipped
    with pytest.raises(ValueError, match="max_torque"):
        jax.jit(run)(jnp.ones(2))
