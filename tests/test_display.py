"""What figures, summaries and reprs show: log floors, Psi >= 0, binned parameters, classes of
heat-map cells, the not-settled fraction, and numbers in reprs."""

import re
import types

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
import pytest

import so3jax as s
from so3jax import _plot_sweep, plot, scenes
from so3jax.__main__ import summarize
from so3jax._plot_log import log_floor, log_line, peak
from so3jax._sweep import DIVERGED, FINITE, NUMERICAL, UNRESOLVED, SweepResult

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

EPS64 = float(np.finfo(np.float64).eps)
SEED_J = (0.0820, 0.0845, 0.1377)


def _drawn_min(ax):
    return min(np.nanmin(np.asarray(line.get_ydata(), float)) for line in ax.lines)


# --------------------------------------------------------------------------
# Log floors
# --------------------------------------------------------------------------


def test_log_line_clips_to_the_floor_and_holds_the_axis():
    fig, ax = plt.subplots()
    y = np.array([0.0, -1.8e-15, np.nan, 1e-3, 2.0])
    floor = log_floor(np.float64, peak(y))
    assert floor == pytest.approx(2.0 * EPS64)
    line = log_line(ax, np.arange(5.0), y, floor=floor)
    shown = np.asarray(line.get_ydata(), float)
    np.testing.assert_array_equal(shown[[0, 1, 3, 4]], [floor, floor, 1e-3, 2.0])
    assert np.isnan(shown[2])  # a gap stays a gap
    assert ax.get_yscale() == "log" and ax.get_ylim()[0] >= floor
    # A second series with a lower floor: the lowest floor holds, nothing is drawn below it.
    log_line(ax, np.arange(3.0), [0.0, 1e-20, 1e-2], floor=1e-18)
    assert ax.get_ylim()[0] >= 1e-18 and _drawn_min(ax) == 1e-18
    assert log_floor(np.float32) == pytest.approx(float(np.finfo(np.float32).eps))
    # Every value at the floor (an exactly conserved quantity): matplotlib would widen the
    # range by a decade each way; the lower limit stays at the floor.
    fig2, ax2 = plt.subplots()
    log_line(ax2, np.arange(3.0), np.zeros(3), floor=1e-9)
    assert ax2.get_ylim()[0] == 1e-9 and ax2.get_ylim()[1] > 1e-9
    plt.close(fig)
    plt.close(fig2)


def test_tracking_figure_of_a_run_from_rest_has_floored_log_panels():
    """Regulation from rest: e_Omega(0) = 0 exactly. The |e_Omega| axis starts at
    eps * (largest |e_Omega| or |Omega|), not at 1e-300; no panel goes below its floor."""
    R0 = s.exp(jnp.array([1.0, -0.5, 0.3]))
    sc = scenes.tracking(SEED_J, s.GeometricGains(8.81, 2.54), R0, jnp.zeros(3), jnp.eye(3))
    traj = s.simulate(sc, s.RKMK4(), 0.01, 200, save_every=2)
    e_om = np.linalg.norm(np.asarray(traj.extras["e_Omega"]), axis=-1)
    assert e_om[0] == 0.0
    om = np.linalg.norm(np.asarray(traj.Omega), axis=-1)
    floor = EPS64 * max(e_om.max(), om.max())
    fig = plot.tracking_figure(traj)
    by_title = {ax.get_title(): ax for ax in fig.axes}
    ax = by_title["Angular-velocity error"]
    lo, hi = ax.get_ylim()
    assert floor * (1 - 1e-12) <= lo < 1e-12 and hi > e_om.max()
    drawn = np.asarray(ax.lines[0].get_ydata(), float)
    assert drawn[0] == pytest.approx(floor, rel=1e-12) and drawn.min() >= floor * (1 - 1e-12)
    np.testing.assert_array_equal(drawn[e_om > floor], e_om[e_om > floor])
    # Psi resolves angles down to eps: its floor is eps^2; the orthogonality panel eps / 100.
    assert by_title["Attitude error"].get_ylim()[0] >= EPS64**2 * (1 - 1e-12)
    assert _drawn_min(by_title["Attitude error"]) >= EPS64**2 * (1 - 1e-12)
    assert by_title["Orthogonality error"].get_ylim()[0] >= EPS64 / 100 * (1 - 1e-12)
    plt.close(fig)


def _fake_quadrotor_run(psi):
    n = len(psi)
    t = np.linspace(0.0, 1.0, n)
    zeros = np.zeros((n, 3))
    return types.SimpleNamespace(
        t=t,
        R=np.broadcast_to(np.eye(3), (n, 3, 3)),
        Rd=None,
        M=zeros,
        extras={"x": zeros, "x_d": zeros, "e_x": zeros + 0.1, "Psi": np.asarray(psi), "f": t},
        status=types.SimpleNamespace(message=lambda: "finite to the end"),
    )


def test_psi_below_zero_is_clamped_for_display_only():
    """A trace-formula Psi of -1.8e-15 (round-off) prints as 0 and plots at the floor, while
    `attitude_error_function` keeps returning what it computed."""
    traj = _fake_quadrotor_run([0.5, 1e-3, -1.8e-15])
    out = summarize(traj, None)
    assert out["Psi_initial"] == 0.5 and out["Psi_final"] == 0.0
    fig = plot.quadrotor_figure(traj)
    ax = next(a for a in fig.axes if a.get_yscale() == "log")
    assert ax.get_ylim()[0] >= EPS64 and _drawn_min(ax) == EPS64
    plt.close(fig)
    # The library function is not clamped: some rotation gives a negative round-off.
    values = [
        float(s.attitude_error_function(R, R))
        for R in (s.random_rotation(jax.random.key(k)) for k in range(20))
    ]
    assert min(values) < 0


# --------------------------------------------------------------------------
# Sweep summaries and heat maps (results built directly: the summaries only read arrays)
# --------------------------------------------------------------------------


def _result(settling_time, outcome, params=None, grid_shape=None, cost=None):
    G, N = settling_time.shape
    rng = np.random.default_rng(1)
    k = np.geomspace(1.0, 10.0, G)
    if grid_shape is not None:
        kR = np.repeat(np.geomspace(1.0, 10.0, grid_shape[0]), grid_shape[1])
        kO = np.tile(np.geomspace(0.5, 5.0, grid_shape[1]), grid_shape[0])
    else:
        kR, kO = k, k / 2
    failed = (outcome == DIVERGED) | (outcome == UNRESOLVED)
    return SweepResult(
        k_R=kR,
        k_Omega=kO,
        grid_shape=grid_shape,
        R0=np.broadcast_to(np.eye(3), (N, 3, 3)),
        Omega0=np.zeros((N, 3)),
        final_psi=rng.uniform(0, 0.1, (G, N)),
        settling_time=np.where(failed, np.nan, settling_time),
        peak_torque=rng.uniform(1, 2, (G, N)),
        cost=rng.uniform(1, 2, (G, N)) if cost is None else cost,
        status_code=np.zeros((G, N), int),
        fail_step=np.zeros((G, N), int),
        outcome=outcome,
        run_dt=np.full((G, N), 0.01),
        stable_dt=np.full(G, 0.05),
        threshold=0.01,
        dt=0.01,
        n_steps=300,
        save_every=1,
        refine=4,
        params=params or {},
    )


def _random_outcomes(G, N, seed=0):
    rng = np.random.default_rng(seed)
    t = np.where(rng.uniform(size=(G, N)) < 0.4, np.inf, rng.uniform(0.1, 3.0, (G, N)))
    outcome = rng.choice([FINITE, FINITE, FINITE, NUMERICAL, DIVERGED, UNRESOLVED], (G, N))
    return t, outcome


def _param_block(table, name):
    lines = table.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"by {name}"))
    rows = []
    for line in lines[start + 1 :]:
        if not line.startswith("  "):
            break
        rows.append(line)
    return lines[start], rows


def test_summary_bins_continuous_draws_and_lists_a_grid():
    n_att, combos, G = 64, 3, 2
    N = n_att * combos
    rng = np.random.default_rng(5)
    draws = rng.uniform(0.5, 2.0, n_att)  # one draw per attitude, the same for every combination
    grid = np.array([0.0, 0.05, 0.1])
    params = {
        "inertia_scale": np.repeat(np.tile(draws, combos)[:, None], 3, axis=1),
        "disturbance": np.repeat(grid, n_att)[:, None] * np.array([1.0, -1.0, 0.5]),
        "Omega0": np.tile(rng.normal(size=(n_att, 3)), (combos, 1)),
    }
    t, outcome = _random_outcomes(G, N)
    r = _result(t, outcome, params)
    table = r.summary_table()
    head, rows = _param_block(table, "inertia_scale")
    assert "64 distinct values" in head and 1 < len(rows) <= 4
    _, om_rows = _param_block(table, "Omega0")
    assert 1 < len(om_rows) <= 4 and all(row.lstrip().startswith("|v| in") for row in om_rows)
    _, d_rows = _param_block(table, "disturbance")
    assert len(d_rows) == 3
    summary = r.param_summary()
    for k, v in enumerate(grid):
        row = summary["disturbance"][k]
        assert not row["binned"] and row["value"] == pytest.approx([v, -v, 0.5 * v])
        assert row["label"] in d_rows[k]
        cols = slice(k * n_att, (k + 1) * n_att)
        assert row["settled_fraction"] == pytest.approx(r.settled[:, cols].mean())
    # Quantile bins: about N / 4 columns each, ordered, covering every draw.
    bins = summary["inertia_scale"]
    assert sum(b["runs"] for b in bins) == G * N
    for b in bins:
        assert b["binned"] and b["runs"] == G * N // 4
        inside = (params["inertia_scale"][:, 0] >= b["range"][0]) & (
            params["inertia_scale"][:, 0] <= b["range"][1]
        )
        assert b["settled_fraction"] == pytest.approx(r.settled[:, inside].mean())
    assert all(a["range"][1] < b["range"][0] for a, b in zip(bins[:-1], bins[1:], strict=True))
    assert bins[0]["range"][0] == draws.min() and bins[-1]["range"][1] == draws.max()


def test_not_settled_fraction_counts_every_unsettled_run():
    t, outcome = _random_outcomes(5, 40, seed=3)
    r = _result(t, outcome)
    with_stats = (outcome == FINITE) | (outcome == NUMERICAL)
    independent = np.array(
        [
            sum(not (with_stats[g, i] and np.isfinite(t[g, i])) for i in range(40)) / 40
            for g in range(5)
        ]
    )
    np.testing.assert_allclose(r.not_settled_fraction, independent, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(r.failure_fraction, r.not_settled_fraction)
    summary = r.summary()
    assert summary["best"]["not_settled_fraction"] == summary["best"]["failure_fraction"]


def test_heatmap_draws_unsettled_and_failed_cells_as_their_own_classes():
    """A cell whose median settling time is inf is hatched with its own legend entry, not
    drawn at the top of the colour scale; a cell whose runs all failed is grey."""
    N = 4
    t = np.full((9, N), 1.0)
    outcome = np.full((9, N), FINITE)
    t[1, 1:] = np.inf  # 3 of 4 unsettled: median inf
    t[2, :2] = np.inf  # half unsettled: median (1 + inf) / 2 = inf
    t[3, :1] = np.inf  # one unsettled: a finite median
    t[4] = np.inf  # none settled
    outcome[5] = DIVERGED  # all failed: no median
    r = _result(t, outcome, grid_shape=(3, 3))
    # Independent: the median of n values is inf once half or more are inf.
    stats = ~((outcome == DIVERGED) | (outcome == UNRESOLVED))
    n_inf = np.sum(stats & np.isinf(t), axis=1)
    expect_inf = (stats.sum(axis=1) > 0) & (2 * n_inf >= stats.sum(axis=1))
    np.testing.assert_array_equal(np.flatnonzero(expect_inf), [1, 2, 4])
    fig = _plot_sweep.sweep_heatmaps(r)
    ax = fig.axes[0]
    main = ax.collections[0]
    mask = np.ma.getmaskarray(main.get_array()).reshape(3, 3)
    np.testing.assert_array_equal(mask.ravel(), expect_inf | (stats.sum(axis=1) == 0))
    assert np.ma.max(main.get_array()) <= r.dt * r.n_steps
    hatched = [c for c in ax.collections if c.get_label() == _plot_sweep.UNSETTLED_LABEL]
    assert len(hatched) == 1 and hatched[0].get_hatch()
    drawn = ~np.ma.getmaskarray(hatched[0].get_array()).reshape(-1)
    np.testing.assert_array_equal(drawn, expect_inf)
    labels = [text.get_text() for text in ax.get_legend().get_texts()]
    assert _plot_sweep.UNSETTLED_LABEL in labels and _plot_sweep.FAILED_LABEL in labels
    # The middle panel is the not-settled fraction.
    middle = np.asarray(fig.axes[1].collections[0].get_array()).reshape(-1)
    np.testing.assert_allclose(middle, r.not_settled_fraction)
    plt.close(fig)


# --------------------------------------------------------------------------
# Reprs
# --------------------------------------------------------------------------


def test_reprs_show_small_concrete_leaves():
    assert repr(s.GeometricGains(8.81, 2.54)) == "GeometricGains(k_R=8.81, k_Omega=2.54)"
    assert "k_R=[8.81, 8.81, 8.81]" in repr(s.GeometricGains(jnp.full(3, 8.81), 2.54))
    assert "k_R=8.81" in repr(s.GeometricGains(jnp.float32(8.81), jnp.float32(2.54)))
    assert repr(s.RigidBody([1.0, 2.0, 2.5])).startswith(
        "RigidBody(\n  inertia=[[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 2.5]]"
    )
    qg = s.QuadrotorGains(16.0, 5.6, 8.81, 2.54)
    assert repr(qg) == "QuadrotorGains(k_x=16.0, k_v=5.6, k_R=8.81, k_Omega=2.54)"
    scene = scenes.seed()
    text = repr(scene)
    assert "GeometricGains(k_R=8.81, k_Omega=2.54)" in text and "0.1377" in text
    assert "R=f64[2,3,3]" in text  # 18 entries: equinox's form
    quad = scenes.quadrotor_circle()
    assert "mass=4.34" in repr(quad.vehicle) and "g=9.81" in repr(quad.vehicle)
    assert "k_x=[16.0, 16.0, 16.0]" in repr(quad)


def test_reprs_fall_back_for_large_or_traced_leaves():
    batch = jax.vmap(s.GeometricGains)(jnp.linspace(1.0, 2.0, 20), jnp.ones(20))
    assert repr(batch) == "GeometricGains(k_R=f64[20], k_Omega=f64[20])"
    seen = []

    @jax.jit
    def f(gains):
        seen.append(repr(gains))
        return gains.k_R

    f(s.GeometricGains(8.81, 2.54))
    assert "8.81" not in seen[0] and re.search(r"k_R=(weak_)?f64\[\]", seen[0])
