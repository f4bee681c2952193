"""A sweep across two processes on JAX's multi-controller runtime (`jax.distributed`).

Two local CPU processes form one JAX cluster (gloo collectives); their sweep must
equal a single-process sweep exactly, and resume from the chunk files after an
interruption and after lost chunk files.
"""

import json
import os
import socket
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

import so3jax as s
from so3jax._sweep import RUN_FIELDS

# 2 x 2 gains x 2 attitudes = 8 runs in 4 chunks of 2 (one run per process and chunk).
SWEEP = dict(
    k_R=[2.0, 8.81], k_Omega=[1.0, 2.54], key=5, n_attitudes=2, dt=1e-2, n_steps=50, chunk_size=2
)

_WORKER = textwrap.dedent(
    """
    import sys
    from pathlib import Path

    import jax

    port, pid, folder = sys.argv[1], int(sys.argv[2]), Path(sys.argv[3])
    jax.distributed.initialize(
        coordinator_address=f"127.0.0.1:{port}", num_processes=2, process_id=pid,
        initialization_timeout=60,
    )
    jax.config.update("jax_enable_x64", True)
    from jax.experimental import multihost_utils

    import numpy as np

    import so3jax as s
    from so3jax._sweep import RUN_FIELDS

    assert jax.process_count() == 2 and len(jax.devices()) == 2, jax.devices()
    kw = dict(SWEEP_KW, method=s.LieEuler(), scalarize=False, progress=False)
    kw.update(results_dir=folder / f"chunks_{pid}")  # process 1 never touches its own
    sc = s.scenes.seed()
    calls = []

    def stop_after_second(i, n):
        calls.append(i)
        if i == 1:
            raise KeyboardInterrupt

    try:  # interrupted after two of the four chunks, on both processes
        s.sweep(sc, on_chunk=stop_after_second, **kw)
        raise AssertionError("not interrupted")
    except KeyboardInterrupt:
        pass
    assert calls == [0, 1], calls
    if pid == 0:
        names = sorted(p.name for p in (folder / "chunks_0").glob("chunk_*.npz"))
        assert names == ["chunk_00000.npz", "chunk_00001.npz"], names
    calls.clear()
    resumed = s.sweep(sc, on_chunk=lambda i, n: calls.append(i), **kw)
    assert calls == [2, 3], calls
    resumed.save(folder / f"resumed_{pid}.npz")
    # The default chunk: process 0 decides it for both (here one chunk of the 8 runs).
    calls.clear()
    whole = s.sweep(sc, on_chunk=lambda i, n: calls.append((i, n)),
                    **{**kw, "chunk_size": None, "results_dir": None})  # fmt: skip
    assert calls == [(0, 1)], calls
    for f in RUN_FIELDS:
        assert np.array_equal(getattr(whole, f), getattr(resumed, f), equal_nan=True), f
    # Chunk files lost: only those chunks are computed again.
    multihost_utils.sync_global_devices("saved")
    if pid == 0:
        (folder / "chunks_0" / "chunk_00000.npz").unlink()
        (folder / "chunks_0" / "chunk_00003.npz").unlink()
    multihost_utils.sync_global_devices("deleted")
    calls.clear()
    again = s.sweep(sc, on_chunk=lambda i, n: calls.append(i), **kw)
    assert calls == [0, 3], calls
    again.save(folder / f"again_{pid}.npz")
    # The command line on the same cluster (it joins it only if not yet a member).
    from so3jax._cli_sweep import sweep_main

    argv = ["--n-kR", "2", "--kR-range", "2", "8.81", "--n-kOmega", "2"]
    argv += ["--kOmega-range", "1", "2.54", "--n-attitudes", "2", "--seed", "5"]
    argv += ["--duration", "0.5", "--method", "LieEuler", "--chunk-size", "2", "--quiet"]
    assert sweep_main([*argv, "--out", str(folder / f"cli_{pid}"), "--distributed"]) == 0
    print("WORKER-OK", pid, flush=True)
    """
).replace("SWEEP_KW", repr(SWEEP))


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_two_process_sweep_equals_one_process_and_resumes(tmp_path):
    script = tmp_path / "worker.py"
    script.write_text(_WORKER)
    # One CPU device per process; otherwise the suite's XLA_FLAGS (conftest), so that the
    # workers compile as the reference below does.
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if "device_count" not in f]
    env = dict(os.environ, XLA_FLAGS=" ".join(flags), JAX_PLATFORMS="cpu")
    port = _free_port()
    procs = [
        subprocess.Popen(
            [sys.executable, str(script), str(port), str(i), str(tmp_path)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        for i in range(2)
    ]
    # The reference runs here, in one process, while the workers start up, with the
    # same batch per device as theirs (one run): the same compiled program, so the
    # same numbers bit for bit.
    ref = dict(SWEEP, chunk_size=1)
    one = s.sweep(s.scenes.seed(), **ref, method=s.LieEuler(), scalarize=False, progress=False)
    deadline = time.monotonic() + 120
    logs = []
    try:
        for p in procs:
            out, _ = p.communicate(timeout=max(1.0, deadline - time.monotonic()))
            logs.append(out)
    except subprocess.TimeoutExpired:
        pytest.fail("the two-process sweep hung (no result within 120 s)")
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    for i, (p, out) in enumerate(zip(procs, logs, strict=True)):
        assert p.returncode == 0 and f"WORKER-OK {i}" in out, out[-3000:]
    assert np.isfinite(one.cost).all() and (one.status_code == 0).all()
    for name in ("resumed_0", "resumed_1", "again_0", "again_1"):
        got = s.SweepResult.load(tmp_path / f"{name}.npz")
        for f in RUN_FIELDS:
            np.testing.assert_array_equal(getattr(got, f), getattr(one, f), err_msg=f"{name} {f}")
        np.testing.assert_array_equal(got.R0, one.R0)
        np.testing.assert_array_equal(got.k_Omega, one.k_Omega)
    # Process 0 alone touched its results_dir and the command line's output folder.
    assert not (tmp_path / "chunks_1").exists() and not (tmp_path / "cli_1").exists()
    summary = json.loads((tmp_path / "cli_0" / "summary.json").read_text())
    assert summary["processes"] == 2 and len(summary["devices"]) == 2
    cli = s.SweepResult.load(tmp_path / "cli_0" / "results.npz")
    np.testing.assert_allclose(cli.k_R, one.k_R, rtol=1e-15)
    np.testing.assert_array_equal(cli.status_code, one.status_code)
    np.testing.assert_array_equal(cli.outcome, one.outcome)
    for f in ("final_psi", "cost", "peak_torque"):  # scalarized there: equal to round-off
        np.testing.assert_allclose(getattr(cli, f), getattr(one, f), rtol=1e-12, err_msg=f)


def test_command_line_cluster_options_are_checked(capsys):
    from so3jax._cli_sweep import sweep_main

    for argv, words in (
        (["--num-processes", "0"], "--num-processes"),
        (["--num-processes", "2", "--process-id", "2"], "--process-id"),
        (["--process-id", "-1"], "--process-id"),
    ):
        with pytest.raises(SystemExit) as e:
            sweep_main(argv)
        assert e.value.code == 2
        assert words in capsys.readouterr().err
