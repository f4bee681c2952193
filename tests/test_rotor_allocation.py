"""`Rotors(..., allocation=...)`: plain clipping (unchanged) and roll and pitch before yaw.

The references are independent of so3jax: the allocation matrix ``A`` of Lee, Leok &
McClamroch (CDC 2010) eq. (1) written out and inverted by NumPy, and the priority
order roll/pitch, then collective thrust, then yaw (Smeur, Hoeppener & De Wagter,
IMAV 2017) solved as three lexicographic linear programs by `scipy.optimize.linprog`.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linprog
from scipy.spatial.transform import Rotation

import so3jax as s
from so3jax import scenes
from so3jax._quadrotor import DIFFTUNE_GAINS, DIFFTUNE_INERTIA, DIFFTUNE_MASS

ARM, C_LEE = 0.315, 8e-4  # Lee et al.'s arm d and torque coefficient c (m)
HOVER = DIFFTUNE_MASS * 9.81 / 4  # thrust of one rotor at hover, N
LO, HI = 0.0, 2.0 * HOVER


def np_matrix(d=ARM, c=C_LEE):
    return np.array([[1.0, 1.0, 1.0, 1.0], [0.0, -d, 0.0, d], [d, 0.0, -d, 0.0], [-c, c, -c, c]])


def random_wrenches(rng, n):
    """Commands from gentle (nothing saturates) to far beyond the rotors' reach."""
    f = rng.uniform(-30.0, 110.0, n)
    M12 = rng.uniform(-8.0, 8.0, (n, 2)) * rng.choice([0.05, 0.5, 1.0, 1.5], (n, 1))
    M3 = rng.uniform(-0.12, 0.12, n) * rng.choice([0.0, 0.01, 0.3, 1.0], n)
    return f, np.concatenate([M12, M3[:, None]], 1)


_yaw_last = s.Rotors(ARM, C_LEE, LO, HI, allocation="yaw_last")
command = jax.jit(lambda rotors, f, M: rotors.command(f, M))


def test_unknown_allocation_raises():
    for bad in ("yaw-last", "pseudo_inverse", None, 1):
        with pytest.raises(ValueError, match="allocation"):
            s.Rotors(ARM, C_LEE, LO, HI, allocation=bad)


def test_clip_is_todays_program():
    """The default is bit for bit the formula it always was, and the same program."""
    rotors = s.Rotors(ARM, C_LEE, LO, HI)
    assert rotors.allocation == "clip"

    def today(f, M):  # a copy of the formula before `allocation` existed
        q = 0.25 * f
        m1 = M[..., 0] / (2.0 * rotors.arm)
        m2 = M[..., 1] / (2.0 * rotors.arm)
        m3 = M[..., 2] / (4.0 * rotors.torque_coefficient)
        u = jnp.stack([q + m2 - m3, q - m1 + m3, q - m2 - m3, q + m1 + m3], -1)
        return jnp.clip(u, rotors.thrust_min, rotors.thrust_max)

    f, M = random_wrenches(np.random.default_rng(0), 200)
    np.testing.assert_array_equal(rotors.command(f, M), today(f, M))
    assert str(jax.make_jaxpr(rotors.command)(f, M)) == str(jax.make_jaxpr(today)(f, M))


def test_clip_default_simulation_unchanged(monkeypatch):
    """A quadrotor with default `Rotors` traces to the program of today's formula."""

    def today(self, f, M):
        return jnp.clip(self.allocate(f, M), self.thrust_min, self.thrust_max)

    scene = scenes.quadrotor(
        DIFFTUNE_MASS,
        DIFFTUNE_INERTIA,
        s.QuadrotorGains(*DIFFTUNE_GAINS),
        s.HoverReference(np.zeros(3)),
        R0=Rotation.from_rotvec([2.0, 0.5, 0.0]).as_matrix(),
        rotors=s.Rotors(ARM, C_LEE, LO, HI, time_constant=0.02),
    )

    def trace():
        run = jax.make_jaxpr(lambda sc: s.simulate(sc, s.RKMK4(), dt=0.004, n_steps=5).y)
        return str(run(scene))

    now = trace()
    monkeypatch.setattr(s.Rotors, "command", today)
    assert trace() == now


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_within_bounds_and_exact_where_unsaturated(dtype):
    rotors = s.Rotors(dtype(ARM), dtype(C_LEE), dtype(LO), dtype(HI), allocation="yaw_last")
    f, M = random_wrenches(np.random.default_rng(1), 400)
    f, M = f.astype(dtype), M.astype(dtype)
    got = np.asarray(command(rotors, f, M))
    assert got.dtype == dtype
    assert np.all(got >= rotors.thrust_min) and np.all(got <= rotors.thrust_max)
    plain = np.linalg.solve(np_matrix(), np.c_[f, M].astype(np.float64).T).T
    inside = np.all((plain > LO + 1e-3) & (plain < HI - 1e-3), 1)
    assert 20 < inside.sum() < len(f) - 100  # both kinds of case are drawn
    tol = 1e-5 * HI if dtype == np.float32 else 1e-12 * HI
    np.testing.assert_allclose(got[inside], plain[inside], rtol=0, atol=tol)
    # there it is exactly what plain clipping gives
    clip = s.Rotors(dtype(ARM), dtype(C_LEE), dtype(LO), dtype(HI))
    np.testing.assert_array_equal(got[inside], command(clip, f, M)[inside])


def test_roll_pitch_kept_yaw_given_up():
    """Saturated by yaw: the applied roll, pitch and thrust are the commanded ones."""
    A = np_matrix()
    f, M = random_wrenches(np.random.default_rng(2), 400)
    got = np.asarray(command(_yaw_last, f, M))
    applied = got @ A.T
    plain = np.linalg.solve(A, np.c_[f, M].T).T
    no_yaw = np.linalg.solve(A, np.c_[f, M[:, :2], np.zeros(len(f))].T).T
    fits = np.all((no_yaw >= LO) & (no_yaw <= HI), 1)  # (f, M1, M2, 0) is feasible
    case = fits & np.any((plain < LO) | (plain > HI), 1)
    assert case.sum() > 20
    np.testing.assert_allclose(applied[case, :3], np.c_[f, M[:, :2]][case], rtol=0, atol=1e-9)
    yaw = applied[case, 3] / M[case, 2]
    assert np.all((yaw >= -1e-12) & (yaw < 1.0 - 1e-6))  # same sign, reduced
    # plain clipping loses roll and pitch in the same cases
    clipped = np.clip(plain[case], LO, HI) @ A.T
    assert np.max(np.abs(clipped[:, 1:3] - M[case, :2])) > 1.0


def _lexicographic(f, M, A, lo, hi):
    """Roll/pitch scale, then collective thrust, then yaw fraction, each by `linprog`.

    Variables ``(t1..t4, f', s)``; each stage fixes what the earlier ones found. Stage 2
    keeps the yaw moment at zero (the policy clips the thrust before adding yaw).
    """
    t_bounds = [(lo, hi)] * 4
    # 1. the largest s in [0, 1] with (f', s M1, s M2, 0) feasible for some f'
    Aeq = np.zeros((4, 6))
    Aeq[:, :4] = A
    Aeq[0, 4] = -1.0
    Aeq[1:3, 5] = -M[:2]
    r = linprog(
        [0, 0, 0, 0, 0, -1.0],
        A_eq=Aeq,
        b_eq=np.zeros(4),
        bounds=t_bounds + [(None, None), (0.0, 1.0)],
    )
    assert r.status == 0
    scale = r.x[5]
    # 2. f' closest to f with (f', scale M1, scale M2, 0) feasible: minimise e >= |f' - f|
    Aeq = np.zeros((4, 6))
    Aeq[:, :4] = A
    Aeq[0, 4] = -1.0
    b = np.r_[0.0, scale * M[:2], 0.0]
    Aub = np.array([[0, 0, 0, 0, 1.0, -1.0], [0, 0, 0, 0, -1.0, -1.0]])
    r = linprog(
        [0, 0, 0, 0, 0, 1.0],
        A_ub=Aub,
        b_ub=[f, -f],
        A_eq=Aeq,
        b_eq=b,
        bounds=t_bounds + [(None, None), (0.0, None)],
    )
    assert r.status == 0
    f_kept = r.x[4]
    # 3. the largest fraction k in [0, 1] of the yaw moment with f', M1', M2' held
    Aeq = np.zeros((4, 5))
    Aeq[:, :4] = A
    Aeq[3, 4] = -M[2]
    b = np.r_[f_kept, scale * M[:2], 0.0]
    r = linprog([0, 0, 0, 0, -1.0], A_eq=Aeq, b_eq=b, bounds=t_bounds + [(0.0, 1.0)])
    assert r.status == 0
    return scale, f_kept, r.x[4]


@pytest.mark.parametrize("lo", [0.0, 2.0])
def test_against_linear_programs(lo):
    A = np_matrix()
    rotors = s.Rotors(ARM, C_LEE, lo, HI, allocation="yaw_last")
    rng = np.random.default_rng(3 + int(lo))
    f, M = random_wrenches(rng, 120)
    M[:40, :2] *= 4.0  # roll and pitch alone beyond reach
    applied = np.asarray(command(rotors, f, M)) @ A.T
    n_scaled = n_yaw_cut = 0
    for i in range(len(f)):
        scale, f_kept, k = _lexicographic(f[i], M[i], A, lo, HI)
        np.testing.assert_allclose(applied[i, 1:3], scale * M[i, :2], rtol=0, atol=1e-7)
        np.testing.assert_allclose(applied[i, 0], f_kept, rtol=0, atol=1e-6)
        if abs(M[i, 2]) > 1e-9:
            np.testing.assert_allclose(applied[i, 3] / M[i, 2], k, rtol=0, atol=1e-6)
        n_scaled += scale < 1.0 - 1e-9
        n_yaw_cut += k < 1.0 - 1e-6
    assert n_scaled > 10 and n_yaw_cut > 30  # the cases exercise every stage


def test_jit_vmap_and_gradients():
    f, M = random_wrenches(np.random.default_rng(4), 64)
    batched = jax.vmap(lambda fi, Mi: _yaw_last.command(fi, Mi))(f, M)
    one_by_one = np.stack([np.asarray(_yaw_last.command(f[i], M[i])) for i in range(8)])
    np.testing.assert_allclose(batched[:8], one_by_one, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(batched, command(_yaw_last, f, M))

    w = jnp.array([0.3, -1.0, 2.0, 0.7])
    grad = jax.jit(jax.vmap(jax.grad(lambda fi, Mi: _yaw_last.command(fi, Mi) @ w, (0, 1))))
    gf, gM = grad(f, M)
    assert np.all(np.isfinite(gf)) and np.all(np.isfinite(gM))
    # every rotor off its limits: the Jacobian is A^-1
    jac = jax.jacfwd(lambda u: _yaw_last.command(u[0], u[1:]))(jnp.array([40.0, 0.5, -0.3, 0.01]))
    np.testing.assert_allclose(jac, np.linalg.inv(np_matrix()), rtol=1e-12, atol=1e-12)
    # with no upper limit, and at zero command: still finite
    free = s.Rotors(ARM, C_LEE, allocation="yaw_last")
    g0 = jax.grad(lambda u: free.command(u[0], u[1:]) @ w)(jnp.zeros(4))
    assert np.all(np.isfinite(g0))


def test_recovery_from_a_large_tilt():
    """150 degrees of tilt and 60 of heading: yaw-last allocation rights the vehicle.

    Lee's vehicle with Lee's c = 8e-4 m and rotors of twice the hover thrust. Under plain
    clipping the yaw moment saturates every rotor and the vehicle stays upside down.
    """
    R0 = (
        Rotation.from_euler("z", 60.0, degrees=True).as_matrix()
        @ Rotation.from_rotvec([np.deg2rad(150.0), 0.0, 0.0]).as_matrix()
    )

    def final(allocation):
        scene = scenes.quadrotor(
            DIFFTUNE_MASS,
            DIFFTUNE_INERTIA,
            s.QuadrotorGains(*DIFFTUNE_GAINS),
            s.HoverReference(np.zeros(3)),
            R0=R0,
            control_period=0.004,
            rotors=s.Rotors(ARM, C_LEE, LO, HI, allocation=allocation),
        )
        traj = s.simulate(scene, s.RKMK4(), dt=0.004, n_steps=300)  # 1.2 s
        R = np.asarray(traj.R)[-1].reshape(3, 3)
        tilt = np.degrees(np.arccos(np.clip(R[2, 2], -1.0, 1.0)))  # angle to upright
        return tilt, float(np.asarray(traj.extras["Psi"])[-1])

    tilt_clip, psi_clip = final("clip")
    tilt_yaw, psi_yaw = final("yaw_last")
    assert tilt_clip > 90.0 and psi_clip > 1.0
    assert tilt_yaw < 15.0 and psi_yaw < 0.1
