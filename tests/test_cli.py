"""The command line: ``python -m so3jax``."""

import json
import os
import subprocess
import sys

import pytest

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
