"""Command line: ``python -m so3jax [run] [options]`` (and ``sweep``, ``tune``).

Simulates a scene (by default the seed scenario: geometric tracking control of
a quadrotor's attitude, Lee, Leok & McClamroch, CDC 2010) with a Lie-group
integrator, prints a summary and writes figures to an output folder.
The command enables float64 in JAX for its own run (``--float32`` to keep
float32); the library itself never changes JAX's configuration.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from ._cli_inertia import (
    add_inertia_option,
    checked_inertia,
    describe_inertia,
    inertia_matrix,
    scene_inertia,
    with_inertia,
)
from ._integrators import METHODS, method_by_name

#: Scenes accepted by --scene: (description, default duration in seconds).
SCENES = {
    "seed": ("geometric tracking of a sinusoidal reference, quadrotor of LLM 2010", 10.0),
    "near-pi": ("geometric regulation from a 179.4-degree error (slow to leave)", 10.0),
    "unwinding": ("quaternion feedback without hysteresis through 180 degrees", 4.0),
    "hysteresis": ("the same with the hybrid (hysteresis) quaternion controller", 4.0),
    "dzhanibekov": ("torque-free spin about the intermediate axis: periodic flips", 20.0),
    "free-body": ("torque-free quadrotor body, generic spin", 10.0),
    "suslov": ("Suslov's nonholonomic body <Omega, a> = 0, J = diag(1, 2, 3)", 20.0),
    "quadrotor-circle": ("quadrotor on SE(3), DiffTune's circle, control held 2.5 ms", 10.0),
    "quadrotor-recovery": ("quadrotor recovering from nearly upside down to hover (LLM 2010)", 6.0),
    "quadrotor-flip": ("quadrotor flip: one vertical loop, upside down at the top", 5.0),
}

#: Quadrotor scenes: their step defaults to the control period (LGVI does not apply).
_QUADROTOR = ("quadrotor-circle", "quadrotor-recovery", "quadrotor-flip")
_QUADROTOR_DT = 0.0025

#: Scenes whose state carries a hybrid controller's memory (LGVI does not apply).
_WITH_MEMORY = ("unwinding", "hysteresis")

MAX_SAVED = 2000


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line on stderr (exit status 2)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text!r}")
    return value


def _save_every(text: str) -> int | None:
    if text == "auto":
        return None
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer (or 'auto')") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _method(text: str) -> str:
    try:
        return method_by_name(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _scene_name(text: str) -> str:
    if text not in SCENES:
        raise argparse.ArgumentTypeError(
            f"unknown scene {text!r} (choose from {', '.join(SCENES)})"
        )
    return text


def _animation_path(text: str) -> Path:
    from ._plot_animate import check_path

    try:
        return check_path(text)
    except (ValueError, RuntimeError) as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def build_parser() -> argparse.ArgumentParser:
    scenes = "\n".join(f"  {k:<12} {d} (default {T:g} s)" for k, (d, T) in SCENES.items())
    parser = _Parser(
        prog="python -m so3jax",
        usage="python -m so3jax [run] [options]   (also: python -m so3jax sweep|tune --help)",
        description=(
            "Simulate rigid-body attitude dynamics and control on SO(3) with a Lie-group "
            "integrator; print a summary and write figures (attitude error Psi and "
            "||R - Rd|| / (2 sqrt 2), |e_Omega|, torques, orthogonality error, body axes "
            "on the sphere) to an output folder."
        ),
        epilog=(
            f"scenes:\n{scenes}\n\nexamples:\n  python -m so3jax --scene near-pi --method CG3\n"
            "  python -m so3jax --inertia 0.082 0.0845 0.1377   (or 9 numbers: the matrix)"
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--scene",
        type=_scene_name,
        default="seed",
        metavar="NAME",
        help=f"what to simulate: {', '.join(SCENES)} (default: seed)",
    )
    parser.add_argument(
        "--method",
        type=_method,
        default="RKMK4",
        metavar="NAME",
        help=f"integrator: {', '.join(METHODS)} (case-insensitive; default: RKMK4)",
    )
    parser.add_argument(
        "--dt",
        type=_positive_float,
        default=None,
        help="step size in seconds (default: 1e-3; 0.0025 for the quadrotor scenes, one step "
        "per control period, which dt must divide)",
    )
    parser.add_argument(
        "--duration",
        type=_positive_float,
        default=None,
        help="simulated time in seconds (default: the scene's, 10 s for seed)",
    )
    parser.add_argument(
        "--save-every",
        type=_save_every,
        default=None,
        metavar="N",
        help=f"keep every N-th step in the figures (default: auto, <= {MAX_SAVED} points)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("so3jax-output"),
        help="output folder, created if needed (default: so3jax-output/)",
    )
    add_inertia_option(
        parser,
        "it replaces the rigid body's (the vehicle's for a quadrotor; dzhanibekov needs "
        "J1 < J2 < J3, suslov starts near the new J's steady rotation)",
    )
    parser.add_argument(
        "--float32", action="store_true", help="simulate in float32 (default: float64)"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--no-plots", action="store_true", help="skip the figures")
    parser.add_argument(
        "--animate",
        type=_animation_path,
        default=None,
        metavar="PATH",
        help="also write an animation of the run to PATH (.gif, or .mp4 with ffmpeg)",
    )
    return parser


def _make_scene(name: str, dtype, inertia=None):
    """The scene ``name`` in ``dtype``, with the body inertia ``inertia`` if given.

    ``inertia`` (3 moments or a `(3, 3)` matrix, checked by `check_inertia` and
    `_scene_inertia_error`) rebuilds the scene by its constructor (`with_inertia`);
    dzhanibekov and suslov, whose initial rate is set from ``J``, are built with it.
    """
    import jax.numpy as jnp

    from . import scenes
    from ._so3 import from_euler_zyx

    if name == "dzhanibekov":
        if inertia is None:
            return scenes.dzhanibekov(dtype=dtype)
        return scenes.dzhanibekov(np.diag(inertia_matrix(inertia)), dtype=dtype)
    if name == "suslov":
        return _suslov_scene(dtype, inertia)
    if name == "free-body":
        pi = jnp.asarray(math.pi, dtype)
        J = scenes.SEED_INERTIA if inertia is None else inertia
        return scenes.free_body(
            jnp.asarray(J, dtype),
            from_euler_zyx(pi / 3, -pi / 4, pi / 6),
            jnp.asarray([2.0, 5.0, -1.0], dtype),
        )
    if name == "seed":
        scene = scenes.seed(dtype)
    elif name == "near-pi":
        scene = scenes.near_pi(dtype=dtype)
    elif name == "unwinding":
        scene = scenes.unwinding(hysteresis=False, dtype=dtype)
    elif name == "hysteresis":
        scene = scenes.unwinding(hysteresis=True, dtype=dtype)
    elif name == "quadrotor-circle":
        scene = scenes.quadrotor_circle(_QUADROTOR_DT, dtype=dtype)
    elif name == "quadrotor-recovery":
        scene = scenes.quadrotor_recovery(_QUADROTOR_DT, dtype=dtype)
    elif name == "quadrotor-flip":
        scene = scenes.quadrotor_flip(_QUADROTOR_DT, dtype=dtype)
    else:
        raise AssertionError(name)
    return scene if inertia is None else with_inertia(scene, inertia)


#: The suslov scene's constraint vector (normalised): no principal axis of diag(1, 2, 3).
_SUSLOV_A = (1.0, 0.6, 0.3)


def _suslov_axes(J):
    """``(a, w)``: the unit constraint vector and the unit steady-rotation axis ``a x J a``.

    ``w`` is ``None`` where ``a`` is a principal axis of ``J`` (``J a`` parallel to ``a``).
    """
    a = np.asarray(_SUSLOV_A) / np.linalg.norm(_SUSLOV_A)
    w = np.cross(a, J @ a)
    n = np.linalg.norm(w)
    return a, (w / n if n > 1e-9 * np.linalg.norm(J @ a) else None)


def _suslov_scene(dtype, inertia=None):
    """Suslov's body, J = diag(1, 2, 3) (or ``inertia``), a = (1, 0.6, 0.3) (no principal axis).

    It starts 0.3 rad (in the constraint plane) from the repelling steady rotation
    ``-Omega*`` (``Omega*`` spans ``a^perp ∩ (J a)^perp``) at 1.5 rad/s, and turns
    over to ``+Omega*``.
    """
    import jax.numpy as jnp

    from . import scenes

    J = np.diag([1.0, 2.0, 3.0]) if inertia is None else inertia_matrix(inertia)
    a, w = _suslov_axes(J)
    Omega0 = 1.5 * (-np.cos(0.3) * w + np.sin(0.3) * np.cross(a, w))
    return scenes.suslov(
        jnp.asarray(J, dtype), jnp.asarray(a, dtype), jnp.eye(3, dtype=dtype), Omega0
    )


def _scene_inertia_error(name: str, inertia) -> str | None:
    """Why scene ``name`` cannot take ``--inertia`` (checked by `check_inertia`), or ``None``."""
    J = inertia_matrix(inertia)
    if name == "dzhanibekov":
        d = np.diag(J)
        if np.any(J != np.diag(d)) or not d[0] < d[1] < d[2]:
            return (
                "scene dzhanibekov spins about e2, the intermediate principal axis: give 3 "
                "principal moments J1 < J2 < J3 (or a diagonal matrix of them), got "
                f"{describe_inertia(inertia)}"
            )
    if name == "suslov" and _suslov_axes(J)[1] is None:
        a = ", ".join(f"{x:g}" for x in _SUSLOV_A)
        return (
            f"scene suslov's constraint vector a = ({a}) / |a| is a principal axis of "
            f"{describe_inertia(inertia)}: no steady rotation to start near (take unequal moments)"
        )
    return None


def _plan(n_steps: int, save_every: int, n_chunks: int = 20) -> list[int]:
    """Chunk sizes in steps: equal chunks (one compilation) plus a remainder chunk."""
    n_blocks = n_steps // save_every
    n_chunks = max(1, min(n_chunks, n_blocks))
    base, rem = divmod(n_blocks, n_chunks)
    sizes = [base * save_every] * n_chunks
    if rem:
        sizes.append(rem * save_every)
    return sizes


def run_chunked(scene, method, dt: float, n_steps: int, save_every: int, progress: bool = True):
    """`simulate` over chunks of the horizon (restarting from ``traj.y``), with a progress bar.

    **Returns:** ``(trajectory, seconds of the first chunk (compilation included),
    seconds of the rest)``.
    """
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np
    from tqdm import tqdm

    from ._simulate import simulate
    from ._trajectory import Status, Trajectory

    sizes = _plan(n_steps, save_every)
    parts, done, first_s = [], 0, 0.0
    code, bad = 0, -1
    t_start = time.perf_counter()
    bar = tqdm(total=n_steps, unit="step", disable=not progress, file=sys.stderr, leave=False)
    try:
        for i, size in enumerate(sizes):
            tic = time.perf_counter()
            tr = simulate(scene, method, dt, size, save_every=save_every, t0=done * dt)
            jax.block_until_ready(tr)
            if i == 0:
                first_s = time.perf_counter() - tic
            parts.append(tr)
            bar.update(size)
            if not bool(tr.status.ok):
                code, bad = int(tr.status.code), done + int(tr.status.step)
                break
            done += size
            scene = eqx.tree_at(lambda s: s.y0, scene, tr.y)
    finally:
        bar.close()
    rest_s = time.perf_counter() - t_start - first_s

    def cat(name, get):
        arrays = [get(p) for p in parts]
        if arrays[0] is None:
            return None
        arrays = [np.asarray(a) for a in arrays]
        return jax.device_put(np.concatenate([arrays[0]] + [a[1:] for a in arrays[1:]]))

    extras = {k: cat(k, lambda p, k=k: p.extras[k]) for k in parts[0].extras}
    traj = Trajectory(
        t=cat("t", lambda p: p.t),
        R=cat("R", lambda p: p.R),
        Omega=cat("Omega", lambda p: p.Omega),
        Rd=cat("Rd", lambda p: p.Rd),
        M=cat("M", lambda p: p.M),
        extras=extras,
        status=Status(code=jnp.asarray(code), step=jnp.asarray(bad)),
        y=parts[-1].y,
    )
    return traj, first_s, rest_s


def summarize(traj, scene) -> dict:
    """Headline numbers of a run (plain floats)."""
    import numpy as np

    from ._suslov import Suslov
    from .plot import error_function

    R = np.asarray(traj.R, dtype=np.float64)
    t = np.asarray(traj.t, dtype=np.float64)
    ok = np.all(np.isfinite(R), axis=(-1, -2))
    E = np.swapaxes(R[ok], -1, -2) @ R[ok] - np.eye(3)
    out = {
        "t_final": float(t[-1]),
        "status": traj.status.message(),
        "max_orthogonality_error": float(np.sqrt(np.sum(E * E, axis=(-1, -2))).max()),
    }
    if traj.Rd is not None:
        # Psi >= 0: a round-off below zero is shown as 0 (display only).
        psi = np.maximum(error_function(R, np.asarray(traj.Rd, dtype=np.float64)), 0.0)
        M = np.linalg.norm(np.asarray(traj.M, dtype=np.float64), axis=-1)
        out["Psi_initial"] = float(psi[0])
        out["Psi_final"] = float(psi[ok][-1])
        below = np.nonzero(psi < 1e-6)[0]
        out["t_Psi_below_1e-6"] = float(t[below[0]]) if below.size else None
        out["max_abs_M"] = float(np.nanmax(M))
    elif "e_x" in traj.extras:  # a quadrotor
        e_x = np.linalg.norm(np.asarray(traj.extras["e_x"], dtype=np.float64), axis=-1)[ok]
        # The trace formula's round-off can make Psi slightly negative: shown as 0.
        psi = np.maximum(np.asarray(traj.extras["Psi"], dtype=np.float64)[ok], 0.0)
        out["rms_position_error"] = float(np.sqrt(np.mean(e_x**2)))
        out["max_position_error"] = float(e_x.max())
        out["final_position_error"] = float(e_x[-1])
        out["Psi_initial"] = float(psi[0])
        out["Psi_final"] = float(psi[-1])
        out["max_thrust"] = float(np.max(np.asarray(traj.extras["f"], dtype=np.float64)[ok]))
        M = np.linalg.norm(np.asarray(traj.M, dtype=np.float64), axis=-1)
        out["max_abs_M"] = float(np.nanmax(M))
        up = np.asarray(traj.R, dtype=np.float64)[ok][:, 2, 2]  # (-R e3) . (-e3): 1 when level
        out["min_thrust_axis_up"] = float(up.min())
    elif isinstance(scene, Suslov):
        J = np.asarray(scene.body.inertia, dtype=np.float64)
        Om = np.asarray(traj.Omega, dtype=np.float64)[ok]
        T = 0.5 * np.einsum("ni,ij,nj->n", Om, J, Om)
        L = np.linalg.norm(Om @ J.T, axis=-1)
        out["max_rel_energy_error"] = float(np.abs(T / T[0] - 1).max())
        out["max_constraint_residual"] = float(
            np.abs(Om @ np.asarray(scene.a, dtype=np.float64)).max()
        )
        out["abs_J_Omega_initial"] = float(L[0])
        out["abs_J_Omega_final"] = float(L[-1])
        out["max_rel_change_abs_J_Omega"] = float(np.abs(L / L[0] - 1).max())
    else:
        J = np.asarray(scene.body.inertia, dtype=np.float64)
        Om = np.asarray(traj.Omega, dtype=np.float64)[ok]
        T = 0.5 * np.einsum("ni,ij,nj->n", Om, J, Om)
        pi = np.einsum("nij,jk,nk->ni", R[ok], J, Om)
        out["max_rel_energy_error"] = float(np.abs(T / T[0] - 1).max())
        out["max_rel_momentum_error"] = float(
            (np.linalg.norm(pi - pi[0], axis=-1) / np.linalg.norm(pi[0])).max()
        )
        s = np.sign(Om[:, 1])
        out["sign_changes_Omega2"] = int(np.count_nonzero(s[1:] * s[:-1] < 0))
    return out


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def main(argv=None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["sweep"] or argv[:1] == ["tune"]:
        from ._cli_sweep import sweep_main, tune_main

        return (sweep_main if argv[0] == "sweep" else tune_main)(argv[1:])
    if argv[:1] == ["run"]:
        argv = argv[1:]
    args = parser.parse_args(argv)
    if args.method == "LGVI" and args.scene in _QUADROTOR:
        parser.error(
            f"LGVI needs a state (R, Omega) alone; scene {args.scene!r} also carries position "
            "and velocity (use RKMK4, CG3, CF4, ...)"
        )
    if args.dt is None:
        args.dt = _QUADROTOR_DT if args.scene in _QUADROTOR else 1e-3
    elif args.scene in _QUADROTOR:
        ratio = _QUADROTOR_DT / args.dt
        if abs(ratio - round(ratio)) > 1e-6 * ratio or round(ratio) < 1:
            parser.error(
                f"--dt {args.dt:g} must divide the control period {_QUADROTOR_DT:g} s of "
                f"scene {args.scene!r}"
            )
    if args.method == "LGVI" and args.scene in _WITH_MEMORY:
        parser.error(
            f"LGVI needs a state (R, Omega) alone; scene {args.scene!r} also carries the "
            "controller's memory (use RKMK4, CG3, CF4, ...)"
        )
    if args.inertia is not None:
        why = _scene_inertia_error(args.scene, args.inertia)
        if why:
            parser.error(f"argument --inertia: {why}")
    wall0 = time.perf_counter()

    import jax

    if not args.float32:
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    dtype = jnp.float32 if args.float32 else jnp.float64
    with checked_inertia():
        scene = _make_scene(args.scene, dtype, args.inertia)
    inertia = scene_inertia(scene)
    method = METHODS[args.method]()

    duration = SCENES[args.scene][1] if args.duration is None else args.duration
    n_steps = max(1, round(duration / args.dt))
    save_every = args.save_every or max(1, -(-n_steps // MAX_SAVED))
    n_steps = -(-n_steps // save_every) * save_every
    out = args.out
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        parser.error(f"cannot create the output folder {str(out)!r}: {e.strerror}")

    print(
        f"so3jax: scene {args.scene}, method {args.method}, dt {args.dt:g} s, "
        f"{n_steps} steps ({n_steps * args.dt:g} s), saving every {save_every}, "
        f"{jnp.dtype(dtype).name}"
    )
    source = "--inertia" if args.inertia is not None else "the scene's"
    print(f"inertia ({source}): {describe_inertia(inertia)}")
    print("compiling and simulating ...", flush=True)
    traj, first_s, rest_s = run_chunked(
        scene, method, args.dt, n_steps, save_every, progress=not args.no_progress
    )
    print(f"  first chunk (with compilation) {first_s:.2f} s, the rest {rest_s:.2f} s")
    summary = summarize(traj, scene)

    files = []
    if not args.no_plots:
        print("plotting ...", flush=True)
        tic = time.perf_counter()
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from . import plot, scenes

        title = f"{args.scene} ({args.method}, dt = {args.dt:g} s)"
        figs = {"orientation.png": plot.body_axes_figure(traj, title=title)}
        if traj.Rd is not None:
            figs["tracking.png"] = plot.tracking_figure(traj, title=title)
        elif isinstance(scene, scenes.Quadrotor):
            figs["quadrotor.png"] = plot.quadrotor_figure(traj, title=title)
            figs["path.png"] = plot.quadrotor_path(traj, title=title)
        elif isinstance(scene, scenes.Suslov):
            figs["suslov.png"] = plot.suslov_figure(traj, scene, title=title)
        else:
            figs["free_body.png"] = plot.free_body_figure(traj, scene.body, title=title)
        for name, fig in figs.items():
            fig.savefig(out / name, dpi=120)
            plt.close(fig)
            files.append(str(out / name))
        print(f"  {time.perf_counter() - tic:.2f} s")
    if args.animate is not None:
        import matplotlib

        matplotlib.use("Agg")
        from . import plot

        print("animating ...", flush=True)
        files.append(str(plot.animate(traj, args.animate, scene=scene)))

    summary.update(
        scene=args.scene,
        method=args.method,
        dt=args.dt,
        n_steps=n_steps,
        save_every=save_every,
        dtype=jnp.dtype(dtype).name,
        inertia=np.asarray(inertia, np.float64).tolist(),
        inertia_from_option=args.inertia is not None,
        compile_and_first_chunk_s=first_s,
        wall_s=time.perf_counter() - wall0,
        figures=files,
    )
    with open(out / "summary.json", "w") as f:
        json.dump(summary, f, indent=2)

    print("summary:")
    skip = ("figures", "scene", "method", "dt", "n_steps", "inertia_from_option")
    for k in (k for k in summary if k not in skip):
        v = describe_inertia(inertia) if k == "inertia" else _fmt(summary[k])
        print(f"  {k:<28} {v}")
    print(f"output folder: {out.resolve()}")
    for f in files:
        print(f"  {f}")
    return 0 if summary["status"] == "finite to the end" else 1


if __name__ == "__main__":
    sys.exit(main())
