"""Monte Carlo sweeps: reproducibility, chunking, divergence, resuming, sharding, CLI."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import matplotlib
import numpy as np
import pytest

import so3jax as s
from so3jax import _plot_sweep as plots
from so3jax._cli_sweep import sweep_main, tune_main
from so3jax._sweep import RUN_FIELDS

matplotlib.use("Agg")
# k_Omega = 1e3 is past the step limit on purpose: the warning is tested in test_sweep_outcomes.
pytestmark = pytest.mark.filterwarnings("ignore:dt = .* is beyond the stability limit")

K_R = [2.0, 8.81]
# k_Omega = 1e3 is far past RK4's stability limit at dt = 1e-2: a stable step needs 6
# halvings, more than the default refinement budget (4), so those runs are unresolved.
K_OMEGA = [1.0, 2.54, 1e3]
SETTINGS = dict(dt=1e-2, n_steps=100, chunk_size=8, progress=False)


@pytest.fixture(scope="module")
def scene():
    return s.scenes.seed()


@pytest.fixture(scope="module")
def base(scene):
    return s.sweep(scene, K_R, K_OMEGA, key=jax.random.key(3), n_attitudes=4, **SETTINGS)


def assert_same(a, b, rtol=0.0, atol=0.0):
    for f in RUN_FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        assert x.shape == y.shape, f
        np.testing.assert_allclose(x, y, rtol=rtol, atol=atol, err_msg=f)


def test_reproducible_and_sample_i_independent_of_n(scene, base):
    again = s.sweep(scene, K_R, K_OMEGA, key=jax.random.key(3), n_attitudes=4, **SETTINGS)
    assert_same(base, again)
    more = s.sweep(scene, K_R, K_OMEGA, key=jax.random.key(3), n_attitudes=6, **SETTINGS)
    np.testing.assert_array_equal(more.R0[:4], base.R0)
    for f in RUN_FIELDS:
        np.testing.assert_allclose(getattr(more, f)[:, :4], getattr(base, f), rtol=1e-12)
    other = s.sweep(scene, K_R, K_OMEGA, key=jax.random.key(4), n_attitudes=4, **SETTINGS)
    assert not np.allclose(other.R0, base.R0)
    # The attitudes are rotations, and every gain pair sees the same ones.
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", base.R0, base.R0), np.eye(3)[None] + 0 * base.R0, atol=1e-12
    )
    R, _ = s.initial_states(jax.random.key(3), 4)
    np.testing.assert_array_equal(np.asarray(R), base.R0)


def test_chunked_equals_unchunked(scene, base, monkeypatch, engine_policy):
    def default_chunks():
        kw = {**SETTINGS, "chunk_size": None}
        return s.sweep(scene, K_R, K_OMEGA, key=jax.random.key(3), n_attitudes=4, **kw)

    # The default chunk (1024 runs per CPU device, `_sweep.sweep_chunk`) holds all 24 runs:
    # a program for another batch size, equal to round-off (psi = (3 - tr(Rd^T R)) / 2 is
    # formed from numbers of size 1, so it may differ by an ulp of 1).
    assert_same(base, default_chunks(), rtol=1e-12, atol=1e-15)
    # A default cap below the run count spreads the runs evenly: 24 runs under a cap of
    # 10 go as 3 chunks of 8 (the shape `base` compiled), not 10 + 10 + 4 padded to 10.
    from so3jax import _sweep

    sizes, run_chunk = [], _sweep._run_chunk

    def recorded(*args):
        sizes.append(args[7].shape[0])  # k_R of the chunk's runs
        return run_chunk(*args)

    engine_policy(sweep_chunk={"cpu": 10, "gpu": 65536})
    monkeypatch.setattr(_sweep, "_run_chunk", recorded)
    spread = default_chunks()
    assert sizes[:3] == [8, 8, 8]  # then the re-runs of the failed runs
    assert_same(base, spread)


def test_per_run_metrics_against_a_direct_simulation(scene, base):
    from so3jax._tune import with_gains, with_initial_state

    g, i = 4, 2  # k_R = 8.81, k_Omega = 2.54
    sc = with_initial_state(
        with_gains(scene, base.k_R[g], base.k_Omega[g]), base.R0[i], base.Omega0[i]
    )
    traj = s.simulate(sc, s.RKMK4(), 1e-2, 100)
    psi = np.asarray(s.attitude_error_function(traj.R, traj.Rd))
    t = np.asarray(traj.t)
    below = psi < base.threshold
    k = next(j for j in range(len(t)) if below[j:].all()) if below[-1] else None
    expected = t[k] if k is not None else np.inf
    assert base.settling_time[g, i] == expected
    assert base.final_psi[g, i] == pytest.approx(psi[-1], rel=1e-12)
    assert base.peak_torque[g, i] == pytest.approx(
        np.linalg.norm(np.asarray(traj.M), axis=-1).max()
    )
    assert base.cost[g, i] == pytest.approx(float(s.tracking_cost(traj, sc)), rel=1e-12)


def test_failures_past_the_refinement_budget_are_flagged_and_excluded(scene, base):
    # k_Omega = 1e3 fails at dt = 1e-2 because of the step (the loop is stable): not
    # "diverged", but unresolved, since a stable step is 6 halvings away (refine = 4).
    bad = base.k_Omega == 1e3
    assert bad.sum() == 2
    assert base.unresolved[bad].all() and not base.failed[~bad].any()
    assert not base.diverged.any() and not base.numerical.any()
    assert np.all(base.fail_step[bad] >= 0) and np.isnan(base.run_dt[bad]).all()
    assert np.all(base.dt > base.stable_dt[bad]) and np.all(base.dt < base.stable_dt[~bad])
    np.testing.assert_array_equal(base.failure_fraction[bad], 1.0)
    assert np.isnan(base.median_settling_time[bad]).all() and np.isnan(base.mean_cost[bad]).all()
    assert np.isfinite(base.mean_cost[~bad]).all()
    assert not bad[base.best()]
    # The other gain pairs are untouched: the same numbers as a sweep without the bad gain.
    kr, ko = base.k_R[~bad], base.k_Omega[~bad]
    clean = s.sweep(scene, kr, ko, grid=False, key=jax.random.key(3), n_attitudes=4, **SETTINGS)
    for f in ("median_settling_time", "failure_fraction", "mean_cost", "mean_final_psi"):
        np.testing.assert_allclose(getattr(base, f)[~bad], getattr(clean, f), rtol=1e-12)
    json.dumps(base.summary())


def test_interrupted_sweep_resumes_and_loses_nothing(scene, base, tmp_path):
    folder = tmp_path / "runs"
    calls = []

    def stop_after_first(i, n):
        calls.append(i)
        if i == 0:
            raise KeyboardInterrupt

    kw = dict(key=jax.random.key(3), n_attitudes=4, results_dir=folder, **SETTINGS)
    with pytest.raises(KeyboardInterrupt):
        s.sweep(scene, K_R, K_OMEGA, on_chunk=stop_after_first, **kw)
    assert sorted(p.name for p in folder.glob("chunk_*.npz")) == ["chunk_00000.npz"]
    calls.clear()
    resumed = s.sweep(scene, K_R, K_OMEGA, on_chunk=stop_after_first, **kw)
    assert calls == [1, 2]  # chunk 0 was loaded, not recomputed
    assert_same(base, resumed)
    # Losing the last chunk file: only that chunk is recomputed.
    (folder / "chunk_00002.npz").unlink()
    calls.clear()
    again = s.sweep(scene, K_R, K_OMEGA, on_chunk=lambda i, n: calls.append(i), **kw)
    assert calls == [2]
    assert_same(base, again)
    # A different sweep in the same folder is refused unless asked to overwrite.
    with pytest.raises(ValueError, match="different sweep"):
        s.sweep(scene, K_R, K_OMEGA, threshold=0.1, **kw)
    over = s.sweep(scene, K_R, K_OMEGA, threshold=0.1, overwrite=True, **kw)
    np.testing.assert_array_equal(over.cost, base.cost)
    # Save / load round trip.
    base.save(tmp_path / "r.npz")
    loaded = s.SweepResult.load(tmp_path / "r.npz")
    assert_same(base, loaded)
    assert loaded.grid_shape == base.grid_shape and loaded.n_steps == base.n_steps
    assert loaded.scalarize == base.scalarize


_SHARDED = textwrap.dedent(
    """
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    import so3jax as s
    assert len(jax.devices()) == 2, jax.devices()
    sc = s.scenes.seed()
    kw = dict(key=jax.random.key(1), n_attitudes=3, dt=1e-2, n_steps=50, progress=False)
    one = s.sweep(sc, [2.0, 8.0], [1.0, 1e3], devices=jax.devices()[:1], chunk_size=4, **kw)
    two = s.sweep(sc, [2.0, 8.0], [1.0, 1e3], chunk_size=3, **kw)  # rounded up to 4
    fields = ("final_psi", "settling_time", "peak_torque", "cost", "status_code", "fail_step")
    for f in fields + ("outcome", "run_dt"):
        np.testing.assert_allclose(getattr(one, f), getattr(two, f), rtol=1e-12, err_msg=f)
    assert one.unresolved.sum() == 6 and one.diverged.sum() == 0
    print("SHARDED-OK")
    """
)


def test_two_device_sharded_sweep_equals_single_device(tmp_path):
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2"
    env = dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu")
    script = tmp_path / "sharded.py"
    script.write_text(_SHARDED)
    out = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=600
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "SHARDED-OK" in out.stdout


def test_bad_input(scene):
    with pytest.raises(ValueError, match="k_R"):
        s.sweep(scene, [[1.0, 2.0]], [1.0], progress=False)
    with pytest.raises(ValueError, match="pairs"):
        s.sweep(scene, [1.0, 2.0], [1.0], grid=False, progress=False)
    with pytest.raises(ValueError, match="k_Omega"):
        s.sweep(scene, [1.0], [-1.0], progress=False)
    with pytest.raises(ValueError, match="geometric controller"):
        s.sweep(s.scenes.unwinding(), [1.0], [1.0], progress=False)
    with pytest.raises(ValueError, match="threshold"):
        s.sweep(scene, [1.0], [1.0], threshold=3.0, progress=False)
    with pytest.raises(ValueError, match="key"):
        s.sweep(scene, [1.0], [1.0], key="zero", progress=False)


def test_figures(base):
    import matplotlib.pyplot as plt

    for fig in (
        plots.sweep_heatmaps(base),
        plots.settling_distribution(base),
        plots.worst_attitudes(base),
    ):
        assert len(fig.axes) >= 1
        plt.close(fig)
    hist = np.array([3.0, 2.0, 1.5])
    res = s.TuneResult(
        gains=s.GeometricGains(2.0, 1.0),
        cost=1.5,
        initial_cost=3.0,
        cost_history=hist,
        k_R_history=np.array([1.0, 1.5, 2.0]),
        k_Omega_history=np.array([1.0, 1.0, 1.0]),
        best_iteration=2,
    )
    plt.close(plots.tune_figure(res))


def test_command_line(tmp_path, capsys):
    for main in (sweep_main, tune_main):
        with pytest.raises(SystemExit) as e:
            main(["--help"])
        assert e.value.code == 0
        capsys.readouterr()
        with pytest.raises(SystemExit) as e:
            main(["--no-such-option"])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "unrecognized arguments" in err
        with pytest.raises(SystemExit) as e:
            main(["--dt", "-1"])
        assert e.value.code == 2
        assert "--dt" in capsys.readouterr().err
    out = tmp_path / "cli"
    argv = ["--n-kR", "2", "--n-kOmega", "2", "--n-attitudes", "2", "--duration", "0.3"]
    argv += ["--kOmega-range", "0.3", "10"]  # inside the step limit: no refinement to compile
    assert sweep_main([*argv, "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert str(out.resolve()) in printed
    for row in ("settled", "not settled", "numerical", "diverged", "unresolved", "runs/s"):
        assert row in printed, row
    for name in (
        "results.npz",
        "summary.json",
        "heatmaps.png",
        "settling.png",
        "worst_attitudes.png",
    ):
        assert (out / name).exists(), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_runs"] == 8
    assert Path(out / "chunks" / "chunk_00000.npz").exists()
    # A quadrotor: its attitude gains swept, position statistics kept.
    with pytest.raises(SystemExit) as e:
        sweep_main(["--scene", "quadrotor-circle", "--inertia-scale", "2"])
    assert e.value.code == 2 and "--omega0 only" in capsys.readouterr().err
    q = tmp_path / "quad"
    argv = ["--scene", "quadrotor-recovery", "--n-kR", "1", "--n-kOmega", "1"]
    argv += ["--n-attitudes", "2", "--duration", "0.1", "--position-threshold", "0.2"]
    assert sweep_main([*argv, "--out", str(q), "--quiet"]) == 0
    assert "|e_x| < 0.2 m" in capsys.readouterr().out
    res = s.SweepResult.load(q / "results.npz")
    assert res.position_threshold == 0.2 and res.metrics["max_position_error"].shape == (1, 2)
    assert json.loads((q / "summary.json").read_text())["scene"] == "quadrotor-recovery"


def test_scalarized_sweep_equals_array_program(scene, base):
    plain = s.sweep(
        scene, K_R, K_OMEGA, key=jax.random.key(3), n_attitudes=4, scalarize=False, **SETTINGS
    )
    np.testing.assert_array_equal(plain.status_code, base.status_code)
    ok = base.status_code == 0
    for f in ("final_psi", "settling_time", "peak_torque", "cost"):
        np.testing.assert_allclose(
            getattr(base, f)[ok], getattr(plain, f)[ok], rtol=1e-9, atol=1e-14
        )
