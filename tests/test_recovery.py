"""`scenes.quadrotor_recovery`: the paper's upside-down start, against a SciPy closed loop."""

import numpy as np
import pytest
from quadrotor_reference import HoverReference
from scipy.optimize import brentq

import so3jax as s
from so3jax._quadrotor import DIFFTUNE_GAINS, QuadrotorGains

#: Lee, Leok & McClamroch (CDC 2010), numerical example: the vehicle, the gains
#: (k_x = 16 m, k_v = 5.6 m, k_R = 8.81, k_Omega = 2.54) and the upside-down start.
MASS, INERTIA = 4.34, (0.0820, 0.0845, 0.1377)
GAINS = (16.0 * MASS, 5.6 * MASS, 8.81, 2.54)
C, S = 0.9995, 0.0314
DT, T_END = 1e-3, 1.7  # RKMK4, every step saved; past the peak of |x| (near 1.66 s)


def paper_R0():
    """The paper's ``R(0)`` has columns of norm ``hypot(C, S) = 1 - 6.9e-6``: its nearest
    rotation (polar factor) is the rotation by ``atan2(S, -C)`` about ``e1``."""
    c, sn = C / np.hypot(C, S), S / np.hypot(C, S)
    return np.array([[1.0, 0.0, 0.0], [0.0, -c, -sn], [0.0, sn, -c]])


@pytest.fixture(scope="module")
def runs():
    ref = HoverReference(MASS, INERTIA, GAINS)
    sol = ref.solve(paper_R0(), T_END)
    tr = s.simulate(s.scenes.quadrotor_recovery(), s.RKMK4(), DT, round(T_END / DT))
    assert bool(tr.status.ok)
    return ref, sol, tr


def test_recovery_scene_is_the_papers_case():
    sc = s.scenes.quadrotor_recovery()
    assert sc.control_period is None
    for name, k in zip(("k_x", "k_v", "k_R", "k_Omega"), GAINS, strict=True):
        np.testing.assert_allclose(getattr(sc.gains, name), np.full(3, k), rtol=1e-15)
    np.testing.assert_allclose(sc.gains.k_x, 69.44, rtol=1e-15)
    np.testing.assert_allclose(sc.gains.k_v, 24.304, rtol=1e-15)
    np.testing.assert_allclose(sc.vehicle.mass, MASS, rtol=0)
    np.testing.assert_allclose(sc.vehicle.body.inertia, np.diag(INERTIA), rtol=0)
    np.testing.assert_allclose(sc.y0.R[0], paper_R0(), atol=2e-16)
    np.testing.assert_array_equal(sc.y0.x, 0.0)
    # other gains on request (DiffTune's, say)
    g = QuadrotorGains(*DIFFTUNE_GAINS)
    np.testing.assert_array_equal(s.scenes.quadrotor_recovery(gains=g).gains.k_x, 16.0)


def test_recovery_matches_the_scipy_closed_loop(runs):
    ref, sol, tr = runs
    t = np.asarray(tr.t)
    Y = sol.sol(t)
    x, R = np.asarray(tr.extras["x"]), np.asarray(tr.R)
    # RKMK4 at dt = 1e-3 (error ~ dt^4) against DOP853 at 1e-12: the whole path
    err = max(np.abs(x - Y[0:3].T).max(), np.abs(R - Y[6:15].T.reshape(-1, 3, 3)).max())
    print(f"max state error against DOP853: {err:.1e}")
    assert err < 1e-9
    # the library's exact commanded rates against the reference's differences of Rc
    for i in range(0, t.size, 170):
        _, _, Rc, Wc, dWc, psi = ref.control(x[i], tr.extras["v"][i], R[i], tr.Omega[i])
        np.testing.assert_allclose(tr.extras["Rc"][i], Rc, atol=1e-14)
        np.testing.assert_allclose(tr.extras["Omega_c"][i], Wc, atol=1e-9)
        np.testing.assert_allclose(tr.extras["dOmega_c"][i], dWc, atol=1e-8)

    # First time with Psi(R, Rc) < 1. The library's crossing is interpolated linearly
    # between saved points; the reference's is the root of its dense output, and the
    # reference interpolated the same way between the same times.
    psi = np.asarray(tr.extras["Psi"])
    # Psi(R0, Rc(0)) with Rc(0) = I (A = -m g e3, b1_d = e1): 1 + C / hypot(C, S), the
    # paper's 1.9995 (its unprojected matrix) to 6.9e-6
    assert psi[0] == pytest.approx(1.0 + C / np.hypot(C, S), abs=1e-14)
    assert abs(psi[0] - 1.9995) < 1e-5
    i = int(np.flatnonzero(psi < 1.0)[0])
    assert np.all(psi[:i] >= 1.0)
    t0, t1 = t[i - 1], t[i]
    t_lib = t0 + (psi[i - 1] - 1.0) / (psi[i - 1] - psi[i]) * (t1 - t0)

    def g(tt):
        return ref.psi(sol.sol(tt)) - 1.0

    t_star = brentq(g, t0, t1, xtol=1e-15)
    g0, g1 = g(t0), g(t1)
    t_grid = t0 + g0 / (g0 - g1) * (t1 - t0)
    # Same interpolation: only the integration errors differ (states agree to ~4e-11,
    # Psi' = -3.4 / s there).
    assert abs(t_lib - t_grid) < 1e-9
    # Against the exact crossing: linear interpolation errs by at most
    # dt^2 max|Psi''| / (8 |Psi'|) (4.4e-8 s here), from the reference's derivatives.
    h = 1e-4
    d1 = (g(t_star + h) - g(t_star - h)) / (2 * h)
    d2 = max(abs(g(tt + h) - 2 * g(tt) + g(tt - h)) / h**2 for tt in (t0, t_star, t1))
    bound = DT**2 * d2 / (8 * abs(d1))
    print(f"first Psi < 1 at {t_lib:.9f} s (reference {t_star:.9f} s, bound {bound:.1e} s)")
    assert abs(t_lib - t_star) < 1.5 * bound + 1e-9

    # Peak position error: the largest |x| over the saved points against the reference's
    # peak (x . v = 0 there), below it by at most dt^2 |(|x|)''| / 8 from sampling.
    e = np.linalg.norm(x, axis=-1)
    j = int(np.argmax(e))
    assert 0 < j < t.size - 1

    def radial(tt):
        y = sol.sol(tt)
        return y[0:3] @ y[3:6]

    t_peak = brentq(radial, t[j - 1], t[j + 1], xtol=1e-15)
    peak = float(np.linalg.norm(sol.sol(t_peak)[0:3]))
    r = [np.linalg.norm(sol.sol(t_peak + k * h)[0:3]) for k in (-1, 0, 1)]
    sampling = DT**2 * abs(r[0] - 2 * r[1] + r[2]) / h**2 / 8
    print(f"peak |x| {e[j]:.6f} m at t = {t[j]:.3f} s (reference {peak:.6f} m at {t_peak:.4f} s)")
    assert peak - 1.5 * sampling - 1e-9 < e[j] <= peak + 1e-9
