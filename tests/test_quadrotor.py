"""The quadrotor on SE(3): Lee's controller, sampled control, gradients in the 12 gains."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import so3jax as s
from so3jax._quadrotor import (
    DIFFTUNE_GAINS,
    DIFFTUNE_INERTIA,
    DIFFTUNE_MASS,
    CircleReference,
    FigureEightReference,
    HoverReference,
    QuadrotorGains,
    quadrotor,
    quadrotor_circle,
)

M_, J_ = DIFFTUNE_MASS, np.diag(DIFFTUNE_INERTIA)
G0 = np.repeat(np.asarray(DIFFTUNE_GAINS), 3)  # (k_x, k_v, k_R, k_Omega), 3 each
E3 = np.array([0.0, 0.0, 1.0])


def gains_from(p):
    return QuadrotorGains(p[0:3], p[3:6], p[6:9], p[9:12])


def np_hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def np_vee(W):
    return 0.5 * np.array([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]])


# ----------------------------------------------------------------------------
# Hover
# ----------------------------------------------------------------------------


def test_hover_with_zero_error_holds_still():
    p = jnp.array([1.0, -2.0, -3.0])
    for T in (None, 0.01):
        sc = quadrotor(
            2.0, (0.1, 0.12, 0.2), gains_from(G0), HoverReference(p), x0=p, control_period=T
        )
        c = sc.control(jnp.array(0.0), sc.y0)
        if T is None:  # one compiled run (the sampled one) is enough for "stays put"
            continue
        assert float(c.f) == pytest.approx(2.0 * 9.81, rel=1e-15)  # f = m g
        np.testing.assert_array_equal(np.asarray(c.M), 0.0)
        np.testing.assert_array_equal(np.asarray(c.Omega_c), 0.0)
        np.testing.assert_array_equal(np.asarray(c.dOmega_c), 0.0)
        np.testing.assert_allclose(c.Rc, np.eye(3), atol=0)
        tr = s.simulate(sc, s.RKMK4(), 0.005, 200, save_every=50)
        assert bool(tr.status.ok)
        assert np.abs(np.asarray(tr.extras["x"]) - np.asarray(p)).max() < 1e-12
        assert np.abs(np.asarray(tr.R) - np.eye(3)).max() < 1e-14
        assert np.abs(np.asarray(tr.extras["f"]) - 2 * 9.81).max() < 1e-12
        assert np.abs(np.asarray(tr.M)).max() < 1e-12


# ----------------------------------------------------------------------------
# Omega_c, dOmega_c against finite differences of Rc along the closed loop
# ----------------------------------------------------------------------------


def test_commanded_rates_match_finite_differences_of_Rc():
    """Figure-8 from an offset, tilted start (continuous control): every derivative matters."""
    dt = 1e-3
    sc = quadrotor(
        M_,
        DIFFTUNE_INERTIA,
        gains_from(G0),
        FigureEightReference(1.5, 1.2),
        x0=jnp.array([0.3, -0.2, 0.1]),
        v0=jnp.array([0.0, 0.5, 0.0]),
        R0=s.from_euler_zyx(0.3, 0.2, -0.25),
        Omega0=jnp.array([0.5, -0.3, 0.2]),
    )
    tr = s.simulate(sc, s.RKMK4(), dt, 600)
    assert bool(tr.status.ok)
    Rc = np.asarray(tr.extras["Rc"])
    Wc = np.asarray(tr.extras["Omega_c"])
    dWc = np.asarray(tr.extras["dOmega_c"])
    k = np.arange(2, Rc.shape[0] - 2)
    # 4th-order central differences (error ~ dt^4).
    dRc = (Rc[k - 2] - 8 * Rc[k - 1] + 8 * Rc[k + 1] - Rc[k + 2]) / (12 * dt)
    Wc_fd = np.stack([np_vee(Rc[i].T @ d) for i, d in zip(k, dRc, strict=True)])
    dWc_fd = (Wc[k - 2] - 8 * Wc[k - 1] + 8 * Wc[k + 1] - Wc[k + 2]) / (12 * dt)
    err_w = np.abs(Wc_fd - Wc[k]).max() / np.abs(Wc).max()
    err_dw = np.abs(dWc_fd - dWc[k]).max() / np.abs(dWc).max()
    print(f"Omega_c rel err {err_w:.2e}, dOmega_c rel err {err_dw:.2e}")
    assert np.abs(Wc).max() > 0.5 and np.abs(dWc).max() > 1.0  # a real test
    assert err_w < 1e-8 and err_dw < 1e-7
    # Rc is a rotation; Psi is 1/2 tr(I - Rc^T R)
    assert np.abs(np.einsum("nji,njk->nik", Rc, Rc) - np.eye(3)).max() < 1e-13


# ----------------------------------------------------------------------------
# An independent NumPy model: hand-written chain rules (fdcl-style), SciPy DOP853
# ----------------------------------------------------------------------------


def _unit_d2(a, a1, a2):
    """u = a/|a| and its first two derivatives."""
    n = np.linalg.norm(a)
    u = a / n
    n1 = u @ a1
    u1 = (a1 - u * n1) / n
    n2 = u1 @ a1 + u @ a2
    u2 = (a2 - 2 * u1 * n1 - u * n2) / n
    return u, u1, u2


def np_circle(t):
    """DiffTune's circle and its derivatives up to the 4th; b1_d = e1."""
    c, sn = np.cos(t), np.sin(t)
    d = [
        np.array([2 * (1 - c), 2 * sn, 0.1 * sn]),
        np.array([2 * sn, 2 * c, 0.1 * c]),
        np.array([2 * c, -2 * sn, -0.1 * sn]),
        np.array([-2 * sn, -2 * c, -0.1 * c]),
        np.array([-2 * c, 2 * sn, 0.1 * sn]),
    ]
    return d


def np_control(t, x, v, R, W, k, g=9.81):
    kx, kv, kR, kW = k[0:3], k[3:6], k[6:9], k[9:12]
    xd, xd1, xd2, xd3, xd4 = np_circle(t)
    b1d, b1d1, b1d2 = np.array([1.0, 0, 0]), np.zeros(3), np.zeros(3)
    m = M_
    ex, ev = x - xd, v - xd1
    A = -kx * ex - kv * ev - m * g * E3 + m * xd2
    Re3 = R @ E3
    f = -A @ Re3
    ev1 = g * E3 - f / m * Re3 - xd2
    A1 = -kx * ev - kv * ev1 + m * xd3
    Re3_1 = R @ np_hat(W) @ E3
    f1 = -A1 @ Re3 - A @ Re3_1
    ev2 = -(f1 * Re3 + f * Re3_1) / m - xd3
    A2 = -kx * ev1 - kv * ev2 + m * xd4
    b3, b31, b32 = _unit_d2(-A, -A1, -A2)
    C = np.cross(b3, b1d)
    C1 = np.cross(b31, b1d) + np.cross(b3, b1d1)
    C2 = np.cross(b32, b1d) + 2 * np.cross(b31, b1d1) + np.cross(b3, b1d2)
    b2, b21, b22 = _unit_d2(C, C1, C2)
    b1 = np.cross(b2, b3)
    b11 = np.cross(b21, b3) + np.cross(b2, b31)
    b12 = np.cross(b22, b3) + 2 * np.cross(b21, b31) + np.cross(b2, b32)
    Rc, Rc1, Rc2 = (np.column_stack(c) for c in ((b1, b2, b3), (b11, b21, b31), (b12, b22, b32)))
    Wc = np_vee(Rc.T @ Rc1)
    dWc = np_vee(Rc.T @ Rc2)
    eR = np_vee(Rc.T @ R)  # skew part: 1/2 vee(Rc^T R - R^T Rc)
    eW = W - R.T @ Rc @ Wc
    M = -kR * eR - kW * eW + np.cross(W, J_ @ W) - J_ @ (np_hat(W) @ R.T @ Rc @ Wc - R.T @ Rc @ dWc)
    return f, M, ex


def np_rhs(t, y, f, M, g=9.81):
    v, R, W = y[3:6], y[6:15].reshape(3, 3), y[15:18]
    dv = g * E3 - f / M_ * (R @ E3)
    dW = np.linalg.solve(J_, M - np.cross(W, J_ @ W))
    return np.concatenate([v, dv, (R @ np_hat(W)).ravel(), dW])


def test_sampled_control_matches_scipy_dop853():
    T, per, n_hold = 0.01, 4, 100  # hold 10 ms, 4 RKMK4 steps per hold, 1 s
    x0, R0 = np.array([0.5, -0.4, 0.3]), np.asarray(s.from_euler_zyx(0.4, -0.3, 0.2))
    W0 = np.array([0.3, -0.2, 0.1])
    sc = quadrotor_circle(control_period=T)
    sc = quadrotor(
        M_, DIFFTUNE_INERTIA, sc.gains, sc.reference, x0=x0, R0=R0, Omega0=W0, control_period=T
    )
    tr = s.simulate(sc, s.RKMK4(), T / per, per * n_hold, save_every=per)
    assert bool(tr.status.ok)
    y = np.concatenate([x0, np.zeros(3), R0.ravel(), W0])
    for i in range(n_hold):
        t = i * T
        f, M, _ = np_control(t, y[0:3], y[3:6], y[6:15].reshape(3, 3), y[15:18], G0)
        if i in (0, 37):  # the held control is the controller's at the sample
            np.testing.assert_allclose(tr.extras["f"][i], f, rtol=1e-10)
            np.testing.assert_allclose(tr.M[i], M, rtol=1e-9, atol=1e-10)
        sol = solve_ivp(np_rhs, (t, t + T), y, method="DOP853", rtol=1e-13, atol=1e-13, args=(f, M))
        y = sol.y[:, -1]
    err = max(
        np.abs(np.asarray(tr.extras["x"][-1]) - y[0:3]).max(),
        np.abs(np.asarray(tr.extras["v"][-1]) - y[3:6]).max(),
        np.abs(np.asarray(tr.R[-1]) - y[6:15].reshape(3, 3)).max(),
        np.abs(np.asarray(tr.Omega[-1]) - y[15:18]).max(),
    )
    print(f"max error against DOP853 after {n_hold} holds: {err:.2e}")
    assert err < 1e-8


# ----------------------------------------------------------------------------
# The DiffTune loss: gradient in the 12 gains
# ----------------------------------------------------------------------------


def difftune_loss(p, n_steps=120):
    sc = quadrotor_circle(gains=gains_from(p))
    tr = s.simulate(sc, s.RKMK4(), 0.0025, n_steps)
    return jnp.sum(tr.extras["e_x"] ** 2)


def test_difftune_gradient_matches_central_differences():
    p = jnp.asarray(G0)
    value_and_grad = jax.jit(jax.value_and_grad(difftune_loss))
    g_rev = np.asarray(value_and_grad(p)[1])

    def loss(q):  # the value from the compiled gradient: one compilation less
        return float(value_and_grad(q)[0])

    fd = np.zeros(12)
    for i in range(12):
        h = 1e-5 * G0[i]
        e = np.zeros(12)
        e[i] = h
        fd[i] = (loss(p + e) - loss(p - e)) / (2 * h)
    rel = np.abs(g_rev - fd) / np.abs(fd).max()
    print("rel. err of the gradient vs central differences", rel.max())
    assert np.all(np.abs(fd) > 0)
    np.testing.assert_allclose(g_rev, fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())
    # (forward mode through the same 12 gains: test_tune_general_mode_difftune_short)


# ----------------------------------------------------------------------------
# float32, bad input
# ----------------------------------------------------------------------------


def test_float32_sampled_circle():
    # dt = T/2 in float32: sampled at even steps, held over the odd ones.
    sc32 = quadrotor_circle(0.005, dtype=jnp.float32)
    tr = s.simulate(sc32, s.RKMK4(), 0.0025, 800)
    assert tr.R.dtype == jnp.float32 and tr.extras["x"].dtype == jnp.float32
    assert bool(tr.status.ok)
    f = np.asarray(tr.extras["f"])
    assert np.all(f[0:-1:2] == f[1::2])
    assert np.all(f[1::2] != f[2::2])
    tr64 = s.simulate(quadrotor_circle(0.005), s.RKMK4(), 0.0025, 800)
    assert np.abs(np.asarray(tr.extras["x"]) - np.asarray(tr64.extras["x"])).max() < 1e-4
    assert float(s.orthogonality_error(tr.R[-1])) < 1e-5


def test_flip_turns_over():
    from so3jax._quadrotor import quadrotor_flip

    sc = quadrotor_flip()
    tr = s.simulate(sc, s.RKMK4(), 0.002, 2500, save_every=25)
    assert bool(tr.status.ok)
    b3 = np.asarray(tr.R)[:, :, 2]  # body axis e3 in the world (down when level)
    assert b3[:, 2].min() < -0.9  # upside down at the top of the loop
    ex = np.linalg.norm(np.asarray(tr.extras["e_x"]), axis=-1)
    assert ex.max() < 0.5 and ex[-1] < 0.05  # tracked the loop, back at hover


def test_bad_input():
    g = gains_from(G0)
    ref = CircleReference()
    with pytest.raises(ValueError, match="mass"):
        quadrotor(-1.0, DIFFTUNE_INERTIA, g, ref)
    with pytest.raises(ValueError, match="mass"):
        quadrotor(0.0, DIFFTUNE_INERTIA, g, ref)
    with pytest.raises(ValueError, match="inertia"):
        quadrotor(1.0, (1.0, -1.0, 1.0), g, ref)
    with pytest.raises(ValueError, match="inertia"):
        quadrotor(1.0, np.array([[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]]), g, ref)
    with pytest.raises(ValueError, match="reference"):
        quadrotor(1.0, DIFFTUNE_INERTIA, g, lambda t: (jnp.zeros(3), jnp.zeros(2)))
    with pytest.raises(ValueError, match="reference"):
        quadrotor(1.0, DIFFTUNE_INERTIA, g, lambda t: jnp.zeros(3))
    with pytest.raises(TypeError, match="reference"):
        quadrotor(1.0, DIFFTUNE_INERTIA, g, 3.0)
    for T in (0.0, -0.01):
        with pytest.raises(ValueError, match="control_period"):
            quadrotor(1.0, DIFFTUNE_INERTIA, g, ref, control_period=T)
    with pytest.raises(ValueError, match="QuadrotorGains.k_v"):
        QuadrotorGains(1.0, -1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="x0"):
        quadrotor(1.0, DIFFTUNE_INERTIA, g, ref, x0=jnp.zeros(2))
    sc = quadrotor(1.0, DIFFTUNE_INERTIA, g, ref, control_period=0.01)
    with pytest.raises(ValueError, match=r"dt \(0.003\) must divide control_period"):
        s.simulate(sc, s.RKMK4(), 0.003, 10)
    # The batched and jitted entry points check it eagerly (inside jit the period is traced).
    cost = lambda tr: jnp.sum(tr.extras["e_x"] ** 2)  # noqa: E731
    batch = jax.vmap(QuadrotorGains)(*[jnp.ones((1, 3))] * 4)
    for call in (
        lambda: s.tune(sc, cost=cost, dt=0.003, n_steps=10, n_iter=1),
        lambda: s.sweep(sc, [1.0], [1.0], dt=0.003, n_steps=10, progress=False),
        lambda: s.sweep_quadrotor(sc, batch, jnp.eye(3)[None], dt=0.003, n_steps=10),
    ):
        with pytest.raises(ValueError, match=r"dt \(0.003\) must divide control_period"):
            call()
    with pytest.raises(ValueError, match="fixed steps"):
        s.simulate(sc, s.RKMK45(), t1=1.0, rtol=1e-6, atol=1e-6)
    assert eqx.tree_equal(sc.for_step(0.0025, 0.0).steps_per_sample, jnp.asarray(4.0))


def test_tune_general_mode_difftune_short():
    """tune(cost=...): projected gradient descent on the 12 gains, in forward mode and in
    reverse mode (the same iterates)."""
    import optax

    sc = quadrotor_circle()
    kw = dict(
        cost=lambda tr: jnp.sum(tr.extras["e_x"] ** 2),
        dt=0.0025,
        n_steps=120,
        n_iter=3,
        optimizer=optax.sgd(1.0),
        bounds=(0.5, 16.02),
    )
    res = s.tune(sc, gradient="forward", **kw)
    assert res.cost_history.shape == (4,) and res.k_R_history.shape == (4, 3)
    # reverse mode (one start: the discrete adjoint from every step's residuals) descends
    # the same way
    rev = s.tune(sc, gradient="reverse", **kw)
    np.testing.assert_allclose(rev.cost_history, res.cost_history, rtol=1e-10)
    # the same iterates, so the same gradients
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-10),
                 rev.gains_history, res.gains_history)  # fmt: skip
    assert np.all(np.diff(res.cost_history) < 0)
    hist = np.concatenate([np.ravel(a) for a in jax.tree.leaves(res.gains_history)])
    assert hist.min() >= 0.5 and hist.max() <= 16.02  # projected onto the bounds ...
    assert float(np.max(res.gains_history.k_x)) == 16.02  # ... and the upper one was active
    p = np.concatenate(
        [np.asarray(getattr(res.gains, n)) for n in ("k_x", "k_v", "k_R", "k_Omega")]
    )
    assert float(difftune_loss(jnp.asarray(p))) == pytest.approx(res.cost, rel=1e-12)
    with pytest.raises(ValueError, match="per_axis"):
        s.tune(sc, per_axis=True, **kw)
    with pytest.raises(ValueError, match="structure"):
        s.tune(sc, (1.0, 1.0), **kw)


def test_sweep_quadrotor_gains_by_attitudes_with_upside_down_starts():
    from so3jax._quadrotor import RECOVERY_R0, quadrotor_recovery

    sc = quadrotor_recovery(control_period=0.01)
    k = np.asarray(DIFFTUNE_GAINS)
    gains = jax.vmap(QuadrotorGains)(*[jnp.asarray([v, 1.5 * v]) for v in k])
    R0 = jnp.stack([jnp.eye(3), s.project(jnp.asarray(RECOVERY_R0)), s.from_euler_zyx(0, 0, 2.0)])
    out = s.sweep_quadrotor(sc, gains, R0, dt=0.01, n_steps=300, save_every=3)
    assert out["final_position_error"].shape == (2, 3)
    assert np.all(out["status_code"] == 0)
    assert out["min_thrust_axis_up"][0, 0] == pytest.approx(1.0)  # level start stays level
    assert np.all(out["min_thrust_axis_up"][:, 1] < -0.99)  # the upside-down start ...
    assert np.all(out["final_psi"][:, 1] < 1e-3)  # ... recovers its attitude in 3 s
    # a batched run equals the single run
    sc1 = quadrotor(
        M_, DIFFTUNE_INERTIA, gains_from(1.5 * G0), sc.reference, R0=R0[2], control_period=0.01
    )
    tr = s.simulate(sc1, s.RKMK4(), 0.01, 300, save_every=3)
    e = np.linalg.norm(np.asarray(tr.extras["e_x"]), axis=-1)
    np.testing.assert_allclose(out["max_position_error"][1, 2], e.max(), rtol=1e-12)


def test_sweep_takes_quadrotor_scenes(tmp_path):
    """`sweep` over a quadrotor: per-run statistics equal direct runs; failures re-run."""
    from so3jax._quadrotor import quadrotor_recovery

    # Sampled control: upside-down starts recover; no step limit from the feedback.
    # DiffTune's gains (the scene's default is the paper's, whose stiffer position loop
    # keeps every one of these starts finite): one run diverges.
    difftune = gains_from(G0)
    sc = quadrotor_recovery(control_period=0.01, gains=difftune)
    # (The array program compiles faster; the CLI test in test_sweep.py runs the scalarized one.)
    r = s.sweep(sc, [8.81], [2.54], n_attitudes=3, key=2, dt=0.01, n_steps=300, save_every=3,
                position_threshold=1.0, scalarize=False, progress=False)  # fmt: skip
    # No step limit from held feedback: a failure confirmed at half the step is the sampled
    # closed loop diverging
    # (attitude 1 passes the singularity of Rc, Omega_c about 500 rad/s, where a 100 Hz
    # controller loses it); the others are finite, one of them from upside down.
    assert np.all(np.isinf(r.stable_dt)) and list(r.outcome[0]) == [0, 2, 0]
    assert r.R0[2, 2, 2] < 0 and np.isnan(r.metrics["max_position_error"][0, 1])
    assert set(r.metrics) == {
        "final_position_error", "max_position_error", "rms_position_error", "min_thrust_axis_up"
    }  # fmt: skip
    i = 2
    assert r.metrics["min_thrust_axis_up"][0, i] < 0
    assert r.settled[0, i] and r.final_psi[0, i] < r.threshold
    g = eqx.tree_at(lambda q: (q.k_R, q.k_Omega), sc.gains, (jnp.asarray(8.81), jnp.asarray(2.54)))
    one = quadrotor(M_, DIFFTUNE_INERTIA, g, sc.reference, R0=r.R0[i], control_period=0.01)
    tr = s.simulate(one, s.RKMK4(), 0.01, 300, save_every=3)
    e = np.linalg.norm(np.asarray(tr.extras["e_x"]), axis=-1)
    np.testing.assert_allclose(r.metrics["max_position_error"][0, i], e.max(), rtol=1e-12)
    np.testing.assert_allclose(r.peak_torque[0, i], np.linalg.norm(tr.M, axis=-1).max(), 1e-12)
    w = s.CostWeights()
    f = (e**2 + float(w.psi) * np.asarray(tr.extras["Psi"])
         + float(w.omega) * np.sum(np.asarray(tr.extras["e_Omega"]) ** 2, -1)
         + float(w.effort) * np.sum(np.asarray(tr.M) ** 2, -1))  # fmt: skip
    np.testing.assert_allclose(r.cost[0, i], np.trapezoid(f, np.asarray(tr.t)), rtol=1e-12)
    inside = (np.asarray(tr.extras["Psi"]) < r.threshold) & (e < r.position_threshold)
    first = np.flatnonzero(~inside)[-1] + 1
    assert r.settling_time[0, i] == pytest.approx(float(tr.t[first]), abs=1e-12)
    from so3jax._plot_sweep import sweep_heatmaps

    fig = sweep_heatmaps(r)  # no step limit: the right panel shows the position error
    assert fig.axes[2].get_title() == "median final |e_x| (m)"
    # the metrics survive save and load
    path = str(tmp_path / "q.npz")
    r.save(path)
    back = s.SweepResult.load(path)
    assert back.position_threshold == r.position_threshold
    key = "rms_position_error"
    np.testing.assert_array_equal(back.metrics[key], r.metrics[key])

    # Continuous control past RKMK4's step limit (k_Omega = 60): resolved at a smaller step,
    # with every statistic (the position ones too) from that run.
    cont = quadrotor_recovery(control_period=None, gains=difftune)
    with pytest.warns(UserWarning, match="beyond the stability limit"):
        r = s.sweep(cont, [8.81, 8.81], [2.54, 60.0], grid=False, n_attitudes=1, dt=0.01,
                    n_steps=60, save_every=2, scalarize=False, progress=False)  # fmt: skip
    assert r.outcome[0, 0] == 0 and r.outcome[1, 0] == 1  # finite; numerical
    f = round(0.01 / r.run_dt[1, 0])
    g = eqx.tree_at(
        lambda q: (q.k_R, q.k_Omega), cont.gains, (jnp.asarray(8.81), jnp.asarray(60.0))
    )
    one = quadrotor(M_, DIFFTUNE_INERTIA, g, cont.reference, R0=r.R0[0])
    tr = s.simulate(one, s.RKMK4(), 0.01 / f, 60 * f, save_every=2 * f)
    e = np.linalg.norm(np.asarray(tr.extras["e_x"]), axis=-1)
    np.testing.assert_allclose(r.metrics["final_position_error"][1, 0], e[-1], rtol=1e-10)
    np.testing.assert_allclose(r.final_psi[1, 0], tr.extras["Psi"][-1], rtol=1e-8, atol=1e-14)

    with pytest.raises(ValueError, match="Omega0"):
        s.sweep(sc, [1.0], [1.0], params={"inertia_scale": [1.0, 2.0]}, progress=False)
    with pytest.raises(ValueError, match="position_threshold"):
        s.sweep(sc, [1.0], [1.0], position_threshold=0.0, progress=False)
