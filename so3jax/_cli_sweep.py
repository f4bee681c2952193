"""Command line for sweeps and tuning: ``python -m so3jax sweep|tune [options]``.

Both commands run the seed scenario (`scenes.seed`; ``--inertia`` rebuilds it with
another body inertia, `with_inertia`) with defaults that finish
in about a minute on a laptop CPU, write their results and figures to an
output folder and print where. float64 runs turn on JAX's x64 mode inside the
command only (`jax.enable_x64` as a context), never globally.

``sweep --distributed`` (or ``--coordinator``, ``--num-processes``,
``--process-id``) runs one sweep over several processes or machines: it calls
`jax.distributed.initialize` before anything touches a JAX device, every
process computes its shard of each chunk, and process 0 alone writes the
output folder. Options left out are detected by JAX (Slurm, Open MPI, ...).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from ._cli_inertia import add_inertia_option, checked_inertia, scene_inertia, with_inertia

#: Scenes `sweep` runs from the command line.
#: (A sweep replaces the initial attitude: quadrotor-recovery is hover at the origin.)
SWEEP_SCENES = ("seed", "quadrotor-recovery", "quadrotor-circle")


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line on stderr (exit status 2)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def _positive(kind):
    def parse(text):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not (math.isfinite(v) and v > 0):
            raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
        return v

    return parse


def _nonneg_float(text):
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (math.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return v


def _common(p: argparse.ArgumentParser, out: str, duration: float):
    p.add_argument("--out", default=out, help="output folder (default: %(default)s)")
    p.add_argument("--duration", type=_positive(float), default=duration, help="horizon in s")
    p.add_argument("--dt", type=_positive(float), default=1e-2, help="step size in s")
    p.add_argument("--method", default="RKMK4", help="Lie-group method (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed of the initial attitudes")
    p.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    p.add_argument("--w-psi", type=_nonneg_float, default=1.0, help="cost weight of Psi")
    p.add_argument("--w-omega", type=_nonneg_float, default=0.1, help="weight of |e_Omega|^2")
    p.add_argument("--w-effort", type=_nonneg_float, default=0.01, help="weight of |M|^2")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _method(name: str, parser):
    from ._integrators import METHODS, method_by_name

    try:
        return METHODS[method_by_name(name)]()
    except ValueError as e:
        parser.error(f"--method: {e}")


def _n_steps(args, parser) -> int:
    n = round(args.duration / args.dt)
    if n < 1 or abs(n * args.dt - args.duration) > 1e-9 * max(1.0, args.duration):
        parser.error(f"--duration ({args.duration}) must be a multiple of --dt ({args.dt})")
    return n


def sweep_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="python -m so3jax sweep",
        description=(
            "Monte Carlo sweep of the geometric controller on the seed scenario (or a "
            "quadrotor, --scene): a log grid of (k_R, k_Omega) crossed with random initial "
            "attitudes. Writes results.npz, summary.json and PNG figures to --out; rerun with "
            "the same options to resume. --inertia gives the body (or vehicle) another inertia."
        ),
    )
    p.add_argument(
        "--scene",
        choices=SWEEP_SCENES,
        default="seed",
        help="the seed's attitude tracking, or a quadrotor on SE(3) whose attitude gains are "
        "swept (its control held over --dt; k_x, k_v as published) (default: %(default)s)",
    )
    p.add_argument("--n-kR", type=int, default=16, help="grid points in k_R")
    p.add_argument("--n-kOmega", type=int, default=16, help="grid points in k_Omega")
    p.add_argument("--kR-range", type=_positive(float), nargs=2, default=(1.0, 100.0))
    p.add_argument("--kOmega-range", type=_positive(float), nargs=2, default=(0.3, 30.0))
    p.add_argument("--n-attitudes", type=int, default=32, help="random attitudes per gain pair")
    p.add_argument("--omega0-std", type=_nonneg_float, default=0.0, help="random rates, rad/s")
    p.add_argument(
        "--inertia-scale",
        type=_positive(float),
        nargs="+",
        help="inertia scale factors to sweep (each on all three axes; crossed with the rest)",
    )
    p.add_argument(
        "--inertia-scale-axes",
        type=_positive(float),
        nargs=3,
        action="append",
        metavar=("S1", "S2", "S3"),
        help="a per-axis inertia scale to sweep (repeat the option for several)",
    )
    p.add_argument(
        "--disturbance",
        type=float,
        nargs=3,
        action="append",
        metavar=("D1", "D2", "D3"),
        help="a constant body disturbance torque in N m to sweep (repeat for several)",
    )
    p.add_argument(
        "--omega0",
        type=float,
        nargs=3,
        action="append",
        metavar=("W1", "W2", "W3"),
        help="an initial body rate in rad/s to sweep (repeat for several)",
    )
    p.add_argument(
        "--reference-amplitude",
        type=_nonneg_float,
        nargs="+",
        help="factors on the reference rate to sweep",
    )
    add_inertia_option(
        p,
        "it replaces the seed's rigid body's or the quadrotor's; --inertia-scale and "
        "--inertia-scale-axes scale it",
    )
    p.add_argument("--threshold", type=_positive(float), default=0.01, help="settling Psi")
    p.add_argument(
        "--position-threshold",
        type=_positive(float),
        default=0.05,
        help="a quadrotor's settling threshold on |e_x| in m (default: %(default)s)",
    )
    p.add_argument("--save-every", type=int, default=1)
    p.add_argument(
        "--chunk-size",
        type=int,
        default=None,
        help="runs per chunk (default: sweep's, 1024 per CPU device, up to 65536 per GPU)",
    )
    p.add_argument(
        "--refine",
        type=int,
        default=4,
        help="halvings of --dt allowed to resolve a run that failed numerically (default: 4)",
    )
    _common(p, "so3jax-sweep", 10.0)
    d = p.add_argument_group(
        "several processes or machines (jax.distributed; process 0 writes --out)"
    )
    d.add_argument(
        "--distributed",
        action="store_true",
        help="join a JAX cluster: jax.distributed.initialize(), which reads Slurm's (or "
        "Open MPI's) environment for whatever of the three options below is left out",
    )
    d.add_argument(
        "--coordinator", metavar="HOST:PORT", help="process 0's address (implies --distributed)"
    )
    d.add_argument("--num-processes", type=int, metavar="N", help="processes in all")
    d.add_argument("--process-id", type=int, metavar="I", help="this process, 0 to N - 1")
    return p


def tune_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="python -m so3jax tune",
        description=(
            "Gradient-based tuning of (k_R, k_Omega) on the seed scenario (Adam in log-gains) "
            "over a batch of initial attitudes (the seed's and random ones). Writes tune.json "
            "and tune.png to --out. --inertia gives the body another inertia."
        ),
    )
    p.add_argument("--kR0", type=_positive(float), default=1.0, help="initial k_R")
    p.add_argument("--kOmega0", type=_positive(float), default=1.0, help="initial k_Omega")
    p.add_argument("--n-attitudes", type=int, default=4, help="attitudes averaged over")
    p.add_argument("--iters", type=int, default=100, help="optimiser steps")
    p.add_argument("--lr", type=_positive(float), default=0.1, help="Adam step in log-gain")
    p.add_argument("--per-axis", action="store_true", help="tune one gain per body axis")
    add_inertia_option(p, "it replaces the seed's rigid body's")
    p.add_argument(
        "--gradient",
        choices=("auto", "reverse", "forward"),
        default="auto",
        help="differentiation mode (auto: forward mode through a few gains, as here)",
    )
    _common(p, "so3jax-tune", 3.0)
    return p


def _check_counts(parser, **counts):
    for name, v in counts.items():
        if v < 1:
            parser.error(f"--{name} must be >= 1, got {v}")


def sweep_main(argv=None) -> int:
    """``python -m so3jax sweep``: run a gain sweep and write its results and figures."""
    parser = sweep_parser()
    args = parser.parse_args(argv)
    _check_counts(
        parser,
        **{
            "n-kR": args.n_kR,
            "n-kOmega": args.n_kOmega,
            "n-attitudes": args.n_attitudes,
            "save-every": args.save_every,
            **({} if args.chunk_size is None else {"chunk-size": args.chunk_size}),
        },
    )
    if args.refine < 0:
        parser.error(f"--refine must be >= 0, got {args.refine}")
    cluster = {
        "coordinator_address": args.coordinator,
        "num_processes": args.num_processes,
        "process_id": args.process_id,
    }
    if args.num_processes is not None and args.num_processes < 1:
        parser.error(f"--num-processes must be >= 1, got {args.num_processes}")
    if args.process_id is not None and not (
        0 <= args.process_id < (args.num_processes or args.process_id + 1)
    ):
        parser.error(f"--process-id must be in [0, --num-processes), got {args.process_id}")
    distributed = args.distributed or any(v is not None for v in cluster.values())
    if args.inertia_scale and args.inertia_scale_axes:
        parser.error("give --inertia-scale or --inertia-scale-axes, not both")
    params = {
        "inertia_scale": args.inertia_scale or args.inertia_scale_axes,
        "disturbance": args.disturbance,
        "Omega0": args.omega0,
        "reference_amplitude": args.reference_amplitude,
    }
    params = {k: v for k, v in params.items() if v}
    if args.scene != "seed" and set(params) - {"Omega0"}:
        parser.error(
            f"--scene {args.scene} sweeps the gains and --omega0 only; --inertia-scale, "
            "--disturbance and --reference-amplitude vary the seed scenario"
        )
    if args.threshold > 2:
        parser.error(f"--threshold must be in (0, 2], got {args.threshold}")
    n_steps = _n_steps(args, parser)
    if n_steps % args.save_every:
        parser.error(f"--save-every ({args.save_every}) must divide the {n_steps} steps")
    method = _method(args.method, parser)

    import jax

    if distributed and not jax.distributed.is_initialized():  # before any device is touched
        jax.distributed.initialize(**{k: v for k, v in cluster.items() if v is not None})
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from . import _plot_sweep as plots, scenes
    from ._sweep import sweep
    from ._tune import CostWeights

    out = Path(args.out)
    first = jax.process_index() == 0
    if first:
        out.mkdir(parents=True, exist_ok=True)
    with jax.enable_x64(args.dtype == "float64"):
        if args.scene == "seed":
            scene = scenes.seed(dtype=args.dtype)
        else:
            make = {
                "quadrotor-recovery": scenes.quadrotor_recovery,
                "quadrotor-circle": scenes.quadrotor_circle,
            }[args.scene]
            scene = make(control_period=args.dt, dtype=args.dtype)
        if args.inertia is not None:
            with checked_inertia():
                scene = with_inertia(scene, args.inertia)
        k_R = np.geomspace(*args.kR_range, args.n_kR)
        k_O = np.geomspace(*args.kOmega_range, args.n_kOmega)
        t = time.perf_counter()
        result = sweep(
            scene,
            k_R,
            k_O,
            key=jax.random.key(args.seed),
            n_attitudes=args.n_attitudes,
            method=method,
            dt=args.dt,
            n_steps=n_steps,
            save_every=args.save_every,
            omega0_std=args.omega0_std,
            params=params,
            threshold=args.threshold,
            position_threshold=args.position_threshold,
            weights=CostWeights(args.w_psi, args.w_omega, args.w_effort),
            refine=args.refine,
            chunk_size=args.chunk_size,
            results_dir=out / "chunks",
            progress=not args.quiet,
        )
        seconds = time.perf_counter() - t
    if not first:  # every process holds the result; process 0 writes it
        return 0
    result.save(out / "results.npz")
    summary = result.summary()
    summary.update(
        scene=args.scene,
        inertia=scene_inertia(scene).astype(float).tolist(),
        seconds=seconds,
        runs_per_second=summary["n_runs"] / seconds,
        dtype=args.dtype,
        method=method.name,
        devices=[str(d) for d in jax.devices()],
        processes=jax.process_count(),
    )
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    figures = {
        "heatmaps.png": plots.sweep_heatmaps(result),
        "settling.png": plots.settling_distribution(result),
        "worst_attitudes.png": plots.worst_attitudes(result),
    }
    for name, fig in figures.items():
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
    best = summary["best"]
    print(result.summary_table())
    print(
        f"{summary['n_runs']} runs in {seconds:.1f} s ({summary['runs_per_second']:.0f} runs/s; "
        f"{summary['numerical_runs']} numerical, {summary['diverged_runs']} diverged); "
        f"best mean cost {best['mean_cost']:.4g} at k_R = {best['k_R']:.3g}, "
        f"k_Omega = {best['k_Omega']:.3g} (median settling {best['median_settling_time']:.3g} s)"
    )
    print(f"results and figures written to {out.resolve()}")
    return 0


def tune_main(argv=None) -> int:
    """``python -m so3jax tune``: tune the seed's gains by gradient and write the history."""
    parser = tune_parser()
    args = parser.parse_args(argv)
    _check_counts(parser, **{"n-attitudes": args.n_attitudes, "iters": args.iters})
    n_steps = _n_steps(args, parser)
    method = _method(args.method, parser)

    import jax
    import jax.numpy as jnp
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from . import _plot_sweep as plots, scenes
    from ._simulate import simulate
    from ._sweep import initial_states
    from ._tune import CostWeights, tune, with_gains

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with jax.enable_x64(args.dtype == "float64"):
        scene = scenes.seed(dtype=args.dtype)
        if args.inertia is not None:
            with checked_inertia():
                scene = with_inertia(scene, args.inertia)
        dtype = scene.y0.R.dtype
        # The seed's own initial attitude first, then random ones.
        R_rand, _ = initial_states(jax.random.key(args.seed), args.n_attitudes - 1, dtype=dtype)
        R0 = jnp.concatenate([scene.y0.R[0][None], R_rand])
        t = time.perf_counter()
        result = tune(
            scene,
            (args.kR0, args.kOmega0),
            method=method,
            dt=args.dt,
            n_steps=n_steps,
            R0=R0,
            weights=CostWeights(args.w_psi, args.w_omega, args.w_effort),
            n_iter=args.iters,
            learning_rate=args.lr,
            per_axis=args.per_axis,
            gradient=args.gradient,
            progress=not args.quiet,
        )
        seconds = time.perf_counter() - t
        before = simulate(with_gains(scene, args.kR0, args.kOmega0), method, args.dt, n_steps)
        after = simulate(
            with_gains(scene, result.gains.k_R, result.gains.k_Omega), method, args.dt, n_steps
        )
    report = {
        "k_R": jnp.asarray(result.gains.k_R).tolist(),
        "k_Omega": jnp.asarray(result.gains.k_Omega).tolist(),
        "cost": result.cost,
        "initial_cost": result.initial_cost,
        "best_iteration": result.best_iteration,
        "cost_history": result.cost_history.tolist(),
        "seconds": seconds,
        "dtype": args.dtype,
        "gradient": result.gradient,
        "n_attitudes": args.n_attitudes,
        "horizon": n_steps * args.dt,
        "inertia": scene_inertia(scene).astype(float).tolist(),
    }
    (out / "tune.json").write_text(json.dumps(report, indent=2) + "\n")
    fig = plots.tune_figure(result, before, after)
    fig.savefig(out / "tune.png", dpi=110)
    plt.close(fig)
    print(
        f"cost {result.initial_cost:.4g} -> {result.cost:.4g} in {args.iters} steps "
        f"({seconds:.1f} s): k_R = {report['k_R']}, k_Omega = {report['k_Omega']}"
    )
    print(f"results and figures written to {out.resolve()}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(sweep_main())
