"""Sweep outcomes: numerical failures told from closed-loop divergence, and step limits."""

import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
import pytest

import so3jax as s
from so3jax import _plot_sweep as plots
from so3jax._scene import Scene
from so3jax._stability import STABILITY_INTERVAL, stability_polynomial
from so3jax._state import LieState, LieTangent
from so3jax._tune import with_gains, with_initial_state

matplotlib.use("Agg")

EXPLICIT = (s.LieEuler, s.CG3, s.RKMK32, s.RKMK4, s.CF4, s.RKMK45)
SEED_J = (0.0820, 0.0845, 0.1377)
# 2 x 2 gain grid x 2 attitudes, 200 steps of 0.01 s: one compiled shape for every sweep here.
K_R = [8.81, 100.0]
KW = dict(key=3, n_attitudes=2, dt=1e-2, n_steps=200, chunk_size=8, progress=False)
KW.update(scalarize=False)


class _Linear(Scene):
    """``x' = L x`` on ``R^2`` (rotation at rest): the test equation ``y' = lambda y`` with
    ``L = [[Re, -Im], [Im, Re]]``, so one step multiplies ``x0 = (1, 0)`` by ``P(h lambda)``."""

    L: jax.Array
    y0: LieState

    def vector_field(self, t, y):
        return LieTangent(jnp.zeros_like(y.R[..., 0]), self.L @ y.x)

    def observe(self, t, y):
        return {"R": y.R[0], "Omega": jnp.zeros(3)}


@eqx.filter_jit
def _one_step(method, z):
    def one(z):
        L = jnp.array([[z.real, -z.imag], [z.imag, z.real]])
        sc = _Linear(L=L, y0=LieState(jnp.eye(3)[None], jnp.array([1.0, 0.0])))
        y1, _ = method.step(sc, jnp.array(0.0), sc.y0, jnp.array(1.0))
        return y1.x[0] + 1j * y1.x[1]

    return jax.vmap(one)(z)


@pytest.mark.parametrize("cls", EXPLICIT, ids=lambda c: c.__name__)
def test_step_limits_against_the_scalar_test_equation(cls):
    """One step of the method itself on ``y' = lambda y`` is ``P(h lambda)``, and the stored
    constant is the real stability interval, rounded down."""
    method = cls()
    interval = s.stability_interval(method)
    const = STABILITY_INTERVAL[method.name]
    assert const <= interval < const + 1e-3
    p = stability_polynomial(method)
    rng = np.random.default_rng(0)
    z = rng.uniform(-4, 0.5, 16) + 1j * rng.uniform(-3, 3, 16)
    np.testing.assert_allclose(
        np.asarray(_one_step(method, jnp.asarray(z))),
        np.polynomial.polynomial.polyval(z, p),
        rtol=1e-12,
        atol=1e-12,
    )
    inside = np.linspace(0.01, 0.999, 50) * -interval
    amp = np.abs(np.asarray(_one_step(method, jnp.asarray(np.append(inside, -1.002 * interval)))))
    assert np.all(amp[:-1] <= 1 + 1e-12) and amp[-1] > 1


def test_stable_dt_follows_the_measured_limits():
    """`stable_dt` (safety 1) against benchmarks/stability.py's largest stable steps on the
    seed scenario with gains x g (README table): within +7 %, and below them with the
    default safety 0.9."""
    g = np.array([1.0, 8.0, 64.0])
    measured = {
        s.LieEuler: [0.071, 0.0081, 0.0010],
        s.CG3: [0.091, 0.010, 0.0013],
        s.RKMK4: [0.100, 0.011, 0.0014],
        s.RKMK45: [0.116, 0.013, 0.0016],
        s.LGVI: [0.064, 0.0079, 0.00099],
    }
    for cls, values in measured.items():
        exact = s.stable_dt(cls(), SEED_J, 8.81 * g, 2.54 * g, safety=1.0)
        ratio = exact / np.asarray(values)
        assert np.all((ratio > 0.97) & (ratio < 1.07)), (cls.__name__, ratio)
        assert np.all(s.stable_dt(cls(), SEED_J, 8.81 * g, 2.54 * g) < np.asarray(values))
    # Overdamped: the fast mode is about k_Omega / J_min.
    lam = s.closed_loop_eigenvalues(np.diag(SEED_J), [8.81], [400.0])
    assert np.max(np.abs(lam)) == pytest.approx(400.0 / SEED_J[0], rel=1e-3)
    # A growing mode sets no limit; an unknown method gives NaN.
    assert np.isinf(s.stable_dt(s.RKMK4(), SEED_J, [8.81], [-40.0])).all()
    with pytest.raises(ValueError, match="safety"):
        s.stable_dt(s.RKMK4(), SEED_J, [1.0], [1.0], safety=0.0)


@pytest.fixture(scope="module")
def stiff():
    with pytest.warns(UserWarning, match=r"dt <= 0.00514 is stable for every pair"):
        return s.sweep(s.scenes.seed(), K_R, [2.54, 40.0], **KW)


def test_step_limit_failures_are_numerical_not_diverged(stiff):
    """k_Omega = 40 at dt = 0.01 is past RKMK4's limit (0.0057 s): every such run fails at
    dt, none is reported diverged; each is resolved at 0.005 s and its statistics equal a
    direct `simulate` there (the saved points at the same times)."""
    r = stiff
    stiff_gain = (r.k_Omega == 40.0)[:, None] & np.ones(r.outcome.shape, bool)
    assert not r.diverged.any() and not r.unresolved.any()
    assert np.all(r.status_code[stiff_gain] != 0)  # they did fail at dt = 0.01
    np.testing.assert_array_equal(r.numerical, stiff_gain)
    np.testing.assert_array_equal(r.run_dt[stiff_gain], 0.005)
    np.testing.assert_array_equal(r.run_dt[~stiff_gain], 0.01)
    np.testing.assert_allclose(r.stable_dt[r.k_Omega == 40.0], 0.00515, rtol=5e-3)
    assert r.settled[stiff_gain].any()
    for g, i in zip(*np.nonzero(stiff_gain), strict=True):
        sc = with_initial_state(
            with_gains(s.scenes.seed(), r.k_R[g], r.k_Omega[g]), r.R0[i], r.Omega0[i]
        )
        traj = s.simulate(sc, s.RKMK4(), 0.005, 400, save_every=2)
        assert int(traj.status.code) == 0
        psi = np.asarray(s.attitude_error_function(traj.R, traj.Rd))
        below = psi < r.threshold
        k = next((j for j in range(psi.size) if below[j:].all()), None)
        assert r.settling_time[g, i] == (np.asarray(traj.t)[k] if k is not None else np.inf)
        assert r.final_psi[g, i] == pytest.approx(psi[-1], rel=1e-12)
        assert r.cost[g, i] == pytest.approx(float(s.tracking_cost(traj, sc)), rel=1e-12)
        peak = np.linalg.norm(np.asarray(traj.M), axis=-1).max()
        assert r.peak_torque[g, i] == pytest.approx(peak, rel=1e-12)
    assert np.isfinite(r.mean_cost).all()
    summary = r.summary()
    json.dumps(summary)
    assert summary["numerical_resolved_at_dt"] == [0.005]
    assert summary["outcomes"]["numerical"] == 4 and summary["diverged_runs"] == 0
    table = r.summary_table()
    assert "resolved at dt = 0.005" in table and "dt <= 0.00514" in table


def test_an_unstable_controller_is_diverged():
    """A negative damping gain (k_Omega = -40) makes the linearised loop grow like
    exp(487 t): the closed loop itself diverges, whatever the step. The geometric
    controller is the only one a sweep drives, and with positive gains and exact
    feed-forward it tracks every smooth reference, so a wrong sign is the honest unstable
    case; negative gains are refused unless asked for."""
    with pytest.raises(ValueError, match="k_Omega must be >= 0.*allow_negative_gains"):
        s.sweep(s.scenes.seed(), K_R, [2.54, -40.0], **KW)
    r = s.sweep(s.scenes.seed(), K_R, [2.54, -40.0], allow_negative_gains=True, **KW)
    bad = (r.k_Omega < 0)[:, None] & np.ones(r.outcome.shape, bool)
    np.testing.assert_array_equal(r.diverged, bad)
    assert not r.numerical.any() and not r.unresolved.any()
    # dt = 0.01 is known stable (no decaying mode limits it); confirmed once at half the step.
    np.testing.assert_array_equal(r.run_dt[bad], 0.005)
    np.testing.assert_array_equal(r.failure_fraction[r.k_Omega < 0], 1.0)
    assert np.isnan(r.mean_cost[r.k_Omega < 0]).all()
    # Without refinement: the failure at a stable dt is diverged at once, and a step-limit
    # failure cannot be resolved.
    with pytest.warns(UserWarning, match="need more than 0 halvings"):
        r0 = s.sweep(s.scenes.seed(), K_R, [40.0, -40.0], allow_negative_gains=True, refine=0, **KW)
    neg = (r0.k_Omega < 0)[:, None] & np.ones(r0.outcome.shape, bool)
    np.testing.assert_array_equal(r0.diverged, neg)
    np.testing.assert_array_equal(r0.unresolved, ~neg)
    np.testing.assert_array_equal(r0.run_dt[neg], 0.01)


def test_chunks_resume_and_old_folders_with_outcomes(stiff, tmp_path):
    folder = tmp_path / "runs"
    calls = []

    def stop(i, n):
        calls.append(i)
        if i == 0:
            raise KeyboardInterrupt

    kw = {**KW, "chunk_size": 4, "results_dir": folder}
    with pytest.warns(UserWarning), pytest.raises(KeyboardInterrupt):
        s.sweep(s.scenes.seed(), K_R, [2.54, 40.0], on_chunk=stop, **kw)
    with np.load(folder / "chunk_00000.npz") as z:
        assert {"outcome", "run_dt"} <= set(z.files)
    calls.clear()
    with pytest.warns(UserWarning):
        resumed = s.sweep(s.scenes.seed(), K_R, [2.54, 40.0], on_chunk=stop, **kw)
    assert calls == [1]
    # (atol: a chunk of 4 runs and the fixture's batch may take different programs, whose
    # round-off differs in the last bits of final_psi's small values; JAX 0.12 saw 4e-16)
    for f in ("final_psi", "settling_time", "peak_torque", "cost", "status_code", "outcome"):
        np.testing.assert_allclose(
            getattr(resumed, f), getattr(stiff, f), rtol=1e-12, atol=1e-14, err_msg=f
        )
    np.testing.assert_array_equal(resumed.run_dt, stiff.run_dt)
    # Save / load keeps the new fields; a file or a chunk folder of the older format is refused.
    stiff.save(tmp_path / "r.npz")
    loaded = s.SweepResult.load(tmp_path / "r.npz")
    np.testing.assert_array_equal(loaded.numerical, stiff.numerical)
    assert loaded.refine == stiff.refine
    with np.load(tmp_path / "r.npz") as z:
        old = {k: z[k] for k in z.files if k not in ("outcome", "run_dt", "stable_dt", "refine")}
    np.savez(tmp_path / "old.npz", **old)
    with pytest.raises(ValueError, match="older so3jax"):
        s.SweepResult.load(tmp_path / "old.npz")
    with np.load(folder / "chunk_00001.npz") as z:
        old = {k: z[k] for k in z.files if k not in ("outcome", "run_dt")}
    np.savez(folder / "chunk_00001.npz", **old)
    with pytest.warns(UserWarning), pytest.raises(ValueError, match="older so3jax"):
        s.sweep(s.scenes.seed(), K_R, [2.54, 40.0], **kw)


def test_bad_input_and_figures(stiff):
    import matplotlib.pyplot as plt

    scene = s.scenes.seed()
    with pytest.raises(ValueError, match="refine"):
        s.sweep(scene, [1.0], [1.0], refine=-1, progress=False)
    with pytest.raises(ValueError, match="safety"):
        s.sweep(scene, [1.0], [1.0], safety=1.5, progress=False)
    with pytest.raises(ValueError, match="k_R must be finite"):
        s.sweep(scene, [math.nan], [1.0], progress=False)
    fig = plots.sweep_heatmaps(stiff)
    assert len(fig.axes) >= 3 and "stable for every cell" in fig._suptitle.get_text()
    plt.close(fig)
    plt.close(plots.settling_distribution(stiff))
    plt.close(plots.worst_attitudes(stiff))


def test_progress_bar_counts_runs(capsys):
    with pytest.warns(UserWarning):
        s.sweep(s.scenes.seed(), K_R, [2.54, 40.0], **{**KW, "progress": True})
    err = capsys.readouterr().err
    assert "8/8" in err and "runs/s" in err and "numerical=4" in err


class _Unknown(s.AbstractLieSolver):
    """RKMK4 behind a method type whose stability region the library does not know."""

    inner: s.RKMK4 = s.RKMK4()

    @property
    def order(self):
        return 4

    def step(self, scene, t, y, h):
        return self.inner.step(scene, t, y, h)


def test_a_method_with_unknown_limit_is_refined_but_never_diverged():
    """Without a known limit, a failure cannot be blamed on the loop: halvings resolve the
    step-limited runs (numerical); the rest stay unresolved, never diverged."""
    assert np.isnan(s.stable_dt(_Unknown(), SEED_J, [1.0], [1.0])).all()
    with pytest.warns(UserWarning, match="not known"):
        r = s.sweep(
            s.scenes.seed(),
            K_R,
            [40.0, -40.0],
            method=_Unknown(),
            refine=1,
            allow_negative_gains=True,
            **KW,
        )
    pos = (r.k_Omega > 0)[:, None] & np.ones(r.outcome.shape, bool)
    np.testing.assert_array_equal(r.numerical, pos)
    np.testing.assert_array_equal(r.unresolved, ~pos)
    assert not r.diverged.any()
