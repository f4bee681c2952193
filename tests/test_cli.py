"""The command line: ``python -m so3jax``."""

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

import so3jax as s
from so3jax.__main__ import _plan, main


def run_cli(*args, cwd):
    env = dict(os.environ, MPLBACKEND="Agg", JAX_PLATFORMS="cpu")
    return subprocess.run(
        [sys.executable, "-m", "so3jax", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


def test_main_command_end_to_end(tmp_path):
    # The bare command (default scene seed, RKMK4, dt 1e-3) with a short horizon.
    r = run_cli("--duration", "0.5", "--no-progress", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    out = tmp_path / "so3jax-output"
    for name in ("tracking.png", "orientation.png"):
        f = out / name
        assert f.is_file() and f.stat().st_size > 10_000
        assert f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert str(out) in r.stdout  # the folder is printed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scene"] == "seed" and summary["method"] == "RKMK4"
    assert summary["n_steps"] == 500 and summary["t_final"] == pytest.approx(0.5)
    assert summary["status"] == "finite to the end"
    # Psi(0) of the seed, then it decreases; the numbers printed are the ones saved.
    assert summary["Psi_initial"] == pytest.approx(0.95362, abs=1e-5)
    assert summary["Psi_final"] < 0.1
    assert 0 < summary["max_abs_M"] < 20
    assert summary["max_orthogonality_error"] < 1e-12
    for key in ("Psi_final", "max_abs_M", "max_orthogonality_error", "wall_s"):
        assert key in r.stdout


def test_run_subcommand_free_body_scene_and_options(tmp_path):
    r = run_cli(
        "run",
        "--scene",
        "dzhanibekov",
        "--method",
        "cg3",
        "--dt",
        "0.01",
        "--duration",
        "3",
        "--save-every",
        "3",
        "--out",
        "figs",
        "--no-progress",
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    out = tmp_path / "figs"
    assert (out / "free_body.png").stat().st_size > 10_000
    assert (out / "orientation.png").stat().st_size > 10_000
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == "CG3" and summary["save_every"] == 3
    assert summary["n_steps"] == 300
    assert summary["max_rel_energy_error"] < 1e-5


@pytest.mark.parametrize(
    "args, words",
    [
        (["--method", "Heun"], ["--method", "unknown method 'Heun'", "RKMK4"]),
        (["--dt", "0"], ["--dt", "positive"]),
        (["--duration", "ten"], ["--duration", "'ten' is not a number"]),
    ],
)
def test_bad_options_exit_2_with_one_line(args, words, tmp_path):
    r = run_cli(*args, cwd=tmp_path)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    for w in words:
        assert w in lines[0]
    assert not (tmp_path / "so3jax-output").exists()


@pytest.mark.parametrize(
    "args, words",
    [
        (["--dt", "-0.001"], ["--dt", "positive"]),
        (["--dt=-1e-3"], ["--dt", "positive"]),
        (["--dt", "inf"], ["--dt", "positive"]),
        (["--duration", "nan"], ["--duration", "positive"]),
        (["--scene", "pendulum"], ["--scene", "unknown scene 'pendulum'", "seed"]),
        (["--save-every", "0"], ["--save-every", ">= 1"]),
        (["--save-every", "2.5"], ["--save-every", "not an integer"]),
        (["--bogus"], ["unrecognized arguments: --bogus"]),
        (["--scene", "unwinding", "--method", "LGVI"], ["LGVI needs"]),
    ],
)
def test_more_bad_options_in_process(args, words, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main([*args, "--out", str(tmp_path / "out")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for w in words:
        assert w in lines[0]


def test_help(tmp_path):
    r = run_cli("--help", cwd=tmp_path)
    assert r.returncode == 0
    for opt in ("--method", "--dt", "--duration", "--out", "--scene", "--save-every"):
        assert opt in r.stdout
    for scene in ("seed", "near-pi", "dzhanibekov", "free-body", "unwinding", "hysteresis"):
        assert scene in r.stdout


def test_chunk_plan():
    for n_steps, save_every in [(10_000, 5), (500, 1), (7, 7), (1003, 1), (300, 3)]:
        sizes = _plan(n_steps, save_every)
        assert sum(sizes) == n_steps
        assert all(k % save_every == 0 and k > 0 for k in sizes)
        assert len(set(sizes)) <= 2  # at most two compilations


def test_suslov_scene(tmp_path, capsys):
    out = tmp_path / "out"
    code = main(
        ["--scene", "suslov", "--dt", "0.01", "--duration", "4", "--no-progress"]
        + ["--out", str(out)]
    )
    assert code == 0
    printed = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scene"] == "suslov" and summary["n_steps"] == 400
    assert summary["max_constraint_residual"] < 1e-13  # RKMK4 keeps <Omega, a> = 0
    assert summary["max_rel_energy_error"] < 1e-8
    assert summary["max_rel_change_abs_J_Omega"] > 0.05  # the free body would keep it
    for key in ("max_constraint_residual", "max_rel_change_abs_J_Omega"):
        assert key in printed
    assert (out / "suslov.png").stat().st_size > 10_000


def test_quadrotor_scene_end_to_end(tmp_path):
    # DiffTune's circle, sampled control: the default step is the control period.
    r = run_cli("--scene", "quadrotor-circle", "--duration", "0.25", "--no-progress", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    out = tmp_path / "so3jax-output"
    for name in ("quadrotor.png", "path.png", "orientation.png"):
        assert (out / name).stat().st_size > 10_000
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dt"] == 0.0025 and summary["n_steps"] == 100
    assert summary["status"] == "finite to the end"
    assert 0 < summary["max_position_error"] < 0.5
    assert summary["max_orthogonality_error"] < 1e-12
    for key in ("rms_position_error", "Psi_final", "max_thrust"):
        assert key in r.stdout


@pytest.mark.parametrize(
    "args, words",
    [
        (["--scene", "quadrotor-flip", "--dt", "0.001"], ["--dt", "must divide", "0.0025"]),
        (["--scene", "quadrotor-recovery", "--method", "LGVI"], ["LGVI needs"]),
    ],
)
def test_quadrotor_bad_options(args, words, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main([*args, "--out", str(tmp_path / "out")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    for w in words:
        assert w in err


# --------------------------------------------------------------------------
# --inertia
# --------------------------------------------------------------------------

J_MOMENTS = [0.1, 0.2, 0.25]
J_MATRIX = [1.0, 0.1, -0.2, 0.1, 2.0, 0.05, -0.2, 0.05, 2.5]  # products of inertia


class _Stop(Exception):
    """Raised by a stand-in once it has recorded the scene it was handed."""


def _record_scene(monkeypatch, module, name, call_through=False):
    """Replace ``module.name`` (run_chunked, sweep or tune) by one that records its scene."""
    seen = {}
    real = getattr(module, name)

    def stand_in(scene, *args, **kwargs):
        seen["scene"] = scene
        if not call_through:
            raise _Stop
        seen["result"] = real(scene, *args, **kwargs)
        return seen["result"]

    monkeypatch.setattr(module, name, stand_in)
    return seen


def _assert_same_scene(a, b):
    la, ta = jax.tree.flatten(a)
    lb, tb = jax.tree.flatten(b)
    assert ta == tb
    for x, y in zip(la, lb, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def _assert_body(body, J):
    J = np.diag(J) if np.shape(J) == (3,) else np.reshape(J, (3, 3))
    np.testing.assert_array_equal(np.asarray(body.inertia), J)
    np.testing.assert_allclose(np.asarray(body.inertia_inv), np.linalg.inv(J), rtol=1e-14)


def test_inertia_reaches_the_seed_and_the_quadrotor(tmp_path, monkeypatch, capsys):
    import so3jax.__main__ as cli
    from so3jax import GeometricGains, SinusoidalRate, scenes
    from so3jax._quadrotor import DIFFTUNE_GAINS, DIFFTUNE_MASS, CircleReference, QuadrotorGains

    seen = _record_scene(monkeypatch, cli, "run_chunked")
    with pytest.raises(_Stop):
        main(["--inertia", *map(str, J_MOMENTS), "--out", str(tmp_path / "a"), "--no-plots"])
    assert f"inertia (--inertia): diag({', '.join(map(str, J_MOMENTS))}) kg m^2" in (
        capsys.readouterr().out
    )
    _assert_body(seen["scene"].body, J_MOMENTS)
    # The same scene as the Python API builds with that inertia (the seed's other settings).
    pi = np.pi
    api = scenes.tracking(
        np.asarray(J_MOMENTS),
        GeometricGains(*scenes.SEED_GAINS),
        s.from_euler_zyx(pi / 3, -pi / 4, pi / 6),
        np.zeros(3),
        np.eye(3),
        SinusoidalRate(),
    )
    _assert_same_scene(seen["scene"], api)

    # A quadrotor: the vehicle's J, and the control held at t = 0 sampled with it.
    with pytest.raises(_Stop):
        main(["--scene", "quadrotor-circle", "--inertia", *map(str, J_MATRIX)])
    J = np.reshape(J_MATRIX, (3, 3))
    _assert_body(seen["scene"].vehicle.body, J)
    api = scenes.quadrotor(
        DIFFTUNE_MASS,
        J,
        QuadrotorGains(*(np.full(3, k) for k in DIFFTUNE_GAINS)),
        CircleReference(2.0, 1.0, 0.1),
        R0=np.eye(3),
        Omega0=np.asarray([0.0, 0.0, 0.001]),
        control_period=0.0025,
    )
    _assert_same_scene(seen["scene"], api)
    default = scenes.quadrotor_circle(0.0025)
    assert not np.allclose(seen["scene"].y0.x[10:13], default.y0.x[10:13])  # held M


def test_inertia_matrix_free_body_run(tmp_path, monkeypatch, capsys):
    # Nine numbers with products of inertia: the torque-free run conserves the energy and
    # the spatial momentum R J Omega of this J (not of the scene's default one).
    import so3jax.__main__ as cli

    seen = _record_scene(monkeypatch, cli, "run_chunked", call_through=True)
    out = tmp_path / "out"
    argv = ["--scene", "free-body", "--inertia", *map(str, J_MATRIX), "--dt", "0.01"]
    code = main([*argv, "--duration", "0.5", "--no-plots", "--no-progress", "--out", str(out)])
    assert code == 0
    J = np.reshape(J_MATRIX, (3, 3))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["inertia"] == J.tolist() and summary["inertia_from_option"]
    printed = capsys.readouterr().out
    assert "[[1, 0.1, -0.2], [0.1, 2, 0.05], [-0.2, 0.05, 2.5]] kg m^2" in printed
    traj = seen["result"][0]
    R, Om = np.asarray(traj.R), np.asarray(traj.Omega)
    T = 0.5 * np.einsum("ni,ij,nj->n", Om, J, Om)
    pi = np.einsum("nij,jk,nk->ni", R, J, Om)
    assert np.abs(T / T[0] - 1).max() < 1e-7
    assert np.linalg.norm(pi - pi[0], axis=-1).max() < 1e-7 * np.linalg.norm(pi[0])
    J0 = np.diag(s.scenes.SEED_INERTIA)  # the scene's own J: its momentum is not conserved
    pi0 = np.einsum("nij,jk,nk->ni", R, J0, Om)
    assert np.linalg.norm(pi0 - pi0[0], axis=-1).max() > 1e-3 * np.linalg.norm(pi0[0])


def test_inertia_reaches_sweep_and_tune(tmp_path, monkeypatch):
    from so3jax import _sweep, _tune
    from so3jax._cli_sweep import sweep_main, tune_main

    seen = _record_scene(monkeypatch, _sweep, "sweep")
    for scene, J in (("seed", J_MATRIX), ("quadrotor-recovery", J_MOMENTS)):
        with pytest.raises(_Stop):
            sweep_main(["--scene", scene, "--inertia", *map(str, J), "--out", str(tmp_path)])
        sc = seen.pop("scene")
        _assert_body(sc.vehicle.body if scene != "seed" else sc.body, J)
        base = s.scenes.seed() if scene == "seed" else s.scenes.quadrotor_recovery(1e-2)
        np.testing.assert_array_equal(sc.y0.R, base.y0.R)  # the rest of the scene kept
    seen = _record_scene(monkeypatch, _tune, "tune")
    with pytest.raises(_Stop):
        tune_main(["--inertia", *map(str, J_MOMENTS), "--out", str(tmp_path)])
    _assert_body(seen["scene"].body, J_MOMENTS)


@pytest.mark.parametrize(
    "values, words",
    [
        (["1", "2"], ["3 principal moments", "9 entries", "got 2 numbers"]),
        (["1", "2", "3", "4"], ["got 4 numbers"]),
        (["1", "2", "heavy"], ["expected a number", "'heavy'"]),
        (["1", "2", "inf"], ["finite", "'inf'"]),
        (["1", "nan", "2"], ["finite", "'nan'"]),
        (["1", "0.1", "0", "0", "2", "0", "0", "0", "3"], ["symmetric", "(1, 2)"]),
        (["1", "2", "0"], ["positive"]),
        (["-1", "2", "2.5"], ["positive"]),
        (["1", "0", "0", "0", "1", "0", "0", "0", "-1"], ["positive definite", "-1"]),
        (["1", "2", "2", "2", "1", "2", "2", "2", "1"], ["positive definite"]),  # eig -1, -1, 5
        (["1", "2", "4"], ["triangle inequality", "J1 + J2 >= J3"]),
        (["4", "1", "2"], ["triangle inequality"]),
        (["1", "0", "0", "0", "1", "0", "0", "0", "3"], ["triangle inequality"]),
    ],
)
def test_bad_inertia_exits_2(values, words, tmp_path, capsys):
    from so3jax._cli_sweep import sweep_main, tune_main

    for command in (main, sweep_main, tune_main):
        with pytest.raises(SystemExit) as exc:
            command(["--inertia", *values, "--out", str(tmp_path / "out")])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in err, err
        for w in ["--inertia", *words]:
            assert w in lines[0], (w, lines[0])
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "args, words",
    [
        (["--scene", "dzhanibekov", "--inertia", "2", "1", "3"], ["J1 < J2 < J3", "e2"]),
        (["--scene", "suslov", "--inertia", "2", "2", "2"], ["suslov", "principal axis"]),
        (["--inertia"], ["--inertia", "expected at least one"]),
    ],
)
def test_inertia_scene_errors(args, words, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main([*args, "--out", str(tmp_path / "out")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    for w in ["--inertia", *words]:
        assert w in err


def test_inertia_help(capsys):
    from so3jax._cli_sweep import sweep_main, tune_main

    for command in (main, sweep_main, tune_main):
        with pytest.raises(SystemExit) as exc:
            command(["--help"])
        assert exc.value.code == 0
        text = " ".join(capsys.readouterr().out.split())
        assert "--inertia J [J ...]" in text and "kg m^2" in text and "9 entries" in text
