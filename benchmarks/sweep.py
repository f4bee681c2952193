"""Throughput of `so3jax.sweep`: runs per second of a gain grid x random attitudes.

The seed scenario (geometric tracking, RKMK4, dt = 1e-2, 10 s) over a
64 x 64 log grid of (k_R, k_Omega) x 16 uniformly random initial attitudes
(65,536 runs), in float64 and float32. Compilation is timed separately (a
warm-up sweep with the same chunk shape, then the whole sweep once: it compiles the
re-runs of runs past the step limit); the figure is the second sweep's runs per second and
body-steps per second, with float32 as a ratio to float64 in the same run.

``sweep`` picks its program per platform (scalarized on a CPU, the array program on a
GPU: `so3jax._engine.policy.Policy.sweep_scalarize`); ``--array`` and ``--scalarized`` force one.
Writes ``results/sweep[-quick].json`` and ``.png`` (forced: ``sweep-array[-quick]``,
``sweep-scalarized[-quick]``).

    python benchmarks/sweep.py            # full
    python benchmarks/sweep.py --quick    # smoke run: 8 x 8 grid x 4 attitudes, LieEuler
    python benchmarks/sweep.py --array    # sweep(..., scalarize=False) beside the default
    python benchmarks/sweep.py --scalarized  # sweep(..., scalarize=True)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402
import numpy as np  # noqa: E402

matplotlib.use("Agg")

import _common as C  # noqa: E402

import so3jax as so3  # noqa: E402
from so3jax import _plot_sweep, _sweep  # noqa: E402
from so3jax._integrators import METHODS, method_by_name  # noqa: E402


def run(
    dtype: str,
    n_grid: int,
    n_att: int,
    n_steps: int,
    chunk: int,
    method: str,
    quick: bool,
    scalarize: bool | None = None,
) -> dict:
    scene = so3.scenes.seed(dtype=dtype)
    k_R = np.geomspace(1.0, 100.0, n_grid)
    k_O = np.geomspace(0.3, 30.0, n_grid)
    kw = dict(
        key=jax.random.key(0),
        dt=1e-2,
        n_steps=n_steps,
        method=METHODS[method](),
        progress=False,
        scalarize=scalarize,
    )
    if chunk is None:  # sweep's own default for these devices and this run
        chunk = _sweep.sweep_chunk(jax.devices(), n_steps + 1, np.dtype(dtype).itemsize)
    chunk = min(chunk, n_grid * n_grid * n_att)
    # Warm-up: one chunk of the same shape (a list of gain pairs x the same
    # attitudes), so the timed sweep reuses everything compiled.
    pairs = np.full(chunk // n_att, 8.81)
    t = time.perf_counter()
    so3.sweep(scene, pairs, pairs, grid=False, n_attitudes=n_att, chunk_size=chunk, **kw)
    compile_s = time.perf_counter() - t
    # The first sweep compiles what the warm-up did not: the re-runs of runs past the
    # step limit at halved steps (new shapes). The second, fully compiled, is the figure.
    # (--quick, a smoke run, times one sweep.)
    t = time.perf_counter()
    result = so3.sweep(scene, k_R, k_O, n_attitudes=n_att, chunk_size=chunk, **kw)
    first_s = seconds = time.perf_counter() - t
    if not quick:
        t = time.perf_counter()
        result = so3.sweep(scene, k_R, k_O, n_attitudes=n_att, chunk_size=chunk, **kw)
        seconds = time.perf_counter() - t
    n_runs = result.cost.size
    return {
        "dtype": dtype,
        "method": method,
        "grid": [n_grid, n_grid],
        "n_attitudes": n_att,
        "n_runs": n_runs,
        "n_steps": n_steps,
        "chunk_size": chunk,
        # The program that ran (sweep's own choice where none was forced).
        "scalarize": _sweep.sweep_scalarize(jax.devices()) if scalarize is None else scalarize,
        "seconds": seconds,
        "first_chunk_with_compile_s": compile_s,
        "first_sweep_s": first_s,
        "runs_per_second": n_runs / seconds,
        "body_steps_per_second": n_runs * n_steps / seconds,
        "diverged_runs": int(result.diverged.sum()),
        # Runs that failed only because dt was past the step limit; their re-runs at a
        # stable step are part of the time above.
        "numerical_runs": int(result.numerical.sum()),
        "summary": result.summary(),
        "_result": result,
    }


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", default=str(Path(__file__).parent / "results"))
    p.add_argument(
        "--chunk-size",
        type=int,
        default=None,
        help="runs per chunk (default: sweep's own, 1024 per CPU device, 65536 per GPU)",
    )
    p.add_argument(
        "--method",
        type=method_by_name,
        default=None,
        help=f"one of {', '.join(METHODS)} (default RKMK4; --quick: LieEuler)",
    )
    p.add_argument(
        "--array",
        action="store_true",
        help="sweep(..., scalarize=False): the array program (writes sweep-array*.json)",
    )
    p.add_argument(
        "--scalarized",
        action="store_true",
        help="sweep(..., scalarize=True): the scalarized program (sweep-scalarized*.json)",
    )
    args = p.parse_args(argv)
    if args.array and args.scalarized:
        p.error("--array and --scalarized are exclusive")
    forced = {"array": False, "scalarized": True}
    program = next((k for k in forced if getattr(args, k)), None)
    # --quick is a smoke run: small sizes and the one-stage method (compiling
    # the scalarized RKMK4 chunk alone takes several seconds).
    n_grid, n_att, n_steps = (8, 4, 200) if args.quick else (64, 16, 1000)
    method = args.method or ("LieEuler" if args.quick else "RKMK4")
    rows = [
        run(dt, n_grid, n_att, n_steps, args.chunk_size, method, args.quick, forced.get(program))
        for dt in ("float64", "float32")
    ]
    for r in rows:
        print(
            f"{r['dtype']}: {r['n_runs']} runs x {n_steps} steps in {r['seconds']:.2f} s: "
            f"{r['runs_per_second']:.0f} runs/s ({r['body_steps_per_second']:.3g} body-steps/s), "
            f"compile+first chunk {r['first_chunk_with_compile_s']:.1f} s, "
            f"first sweep (re-runs compiling) {r['first_sweep_s']:.2f} s"
        )
    ratio = rows[1]["runs_per_second"] / rows[0]["runs_per_second"]
    print(f"float32 / float64 throughput: {ratio:.2f}x")
    args.out = Path(args.out)
    args.out.mkdir(parents=True, exist_ok=True)
    json_path, png_path = C.output_paths(args, f"sweep-{program}" if program else "sweep")
    C.write_json(
        json_path,
        {
            "benchmark": "sweep",
            "quick": args.quick,
            "env": C.environment(),
            "float32_over_float64": ratio,
            "rows": [{k: v for k, v in r.items() if k != "_result"} for r in rows],
        },
    )
    C.save_figure(_plot_sweep.sweep_heatmaps(rows[0]["_result"]), png_path)


if __name__ == "__main__":
    main()
