"""Cost of one gradient of the tracking cost relative to one forward pass.

The mean tracking cost of the seed scenario over B random initial attitudes
(RKMK4, dt = 1e-2), as a function of (k_R, k_Omega), run by the execution
engine (`so3jax._engine`):

- forward pass: the default program (scalarized under `vmap`), the baseline;
- forward pass, array program (``program="array"``);
- reverse (default): with two gains, the engine's one-pass Jacobian (the primal once,
  the two unit tangents batched over it; scalarized in large batches), whose
  contraction with the input tangent JAX transposes;
- reverse, nine-number attitude tangents: the default with the Jacobian program's
  attitude tangents carried as nine numbers (``dR``), not three (``xi``, ``dR = R
  hat(xi)``, `so3jax._engine.passes.frames`);
- reverse, checkpointed: JAX's transpose of the checkpointed array program
  (``program="autodiff"``, memory ~ sqrt(n));
- reverse, discrete adjoint: the engine's own backward scan of ``jax.vjp`` of
  each checkpointed segment (``program="adjoint"``);
- reverse, no checkpoints (JAX's transpose, memory ~ n);
- forward mode (default, `jax.jacfwd`, 2 tangents): the same one-pass Jacobian;
- forward mode, JAX's ``jvp`` of the checkpointed array program
  (``program="autodiff"``);
- Hessian (default, `jax.hessian`: forward over reverse, 2 x 2): the ``jvp`` of the
  engine's one-pass Jacobian program, scalarized from 32 runs;
- Hessian, JAX's autodiff of the checkpointed array program (``program="autodiff"``).

For each: run time (min over repeats, compiled), compile time, and XLA's temp
memory (`compiled.memory_analysis()`), at two horizons and two batch sizes;
ratios are against the default forward pass measured in the same run. Issue 11's
target: a gradient at most 3x that forward pass.

Writes ``results/tune[-quick].json`` and ``.png``. With ``--cost trajectory`` the cost
is a user's own one on saved runs instead (the mean ``tracking_cost(simulate(...))``,
every state saved), for the forward pass, the default reverse pass and ``jacfwd``:
``results/tune-trajectory[-quick].json`` and ``.png``.

    python benchmarks/tune.py            # 10 s and 40 s horizons, B = 16 and 256
    python benchmarks/tune.py --quick    # smoke run: 1 s, B = 2, LieEuler
    python benchmarks/tune.py --cost trajectory
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import _common as C  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402

import so3jax as so3  # noqa: E402
from so3jax import _engine  # noqa: E402
from so3jax._integrators import METHODS, method_by_name  # noqa: E402
from so3jax._tune import with_gains  # noqa: E402

#: The variants, in the order they run (the first is the baseline of the ratios).
VARIANTS = [
    "forward pass",
    "forward pass, array program",
    "reverse (default)",
    "reverse, nine-number attitude tangents",
    "reverse, checkpointed",
    "reverse, discrete adjoint",
    "reverse, no checkpoints",
    "forward mode (jacfwd)",
    "forward mode, JAX's jvp",
    "Hessian (default)",
    "Hessian, autodiff",
]


class nine_numbers:
    """``fn`` traced with the Jacobian programs' attitude tangents carried as nine numbers
    (the ``"frames"`` pass off), for the side-by-side row."""

    def __init__(self, fn):
        self.fn = fn

    def __call__(self, k):
        policy = _engine.policy
        with policy.using(passes=policy.current().passes - {"frames"}):
            return self.fn(k)


def trajectory_cost(scene, k, R0, W0, method, n, program="auto"):
    """A user's own cost on saved runs: the mean `tracking_cost` of `simulate`'s
    trajectories (every state saved), for gains ``k``."""

    def one(R, W):
        sc = with_gains(scene, k[0], k[1])
        return so3.tracking_cost(so3.simulate(sc, method, 1e-2, n, R0=R, Omega0=W), sc)

    if program != "auto":
        raise ValueError("the trajectory cost runs the default program only")
    return jnp.mean(jax.vmap(one)(R0, W0))


def measure(fn, arg, repeats, min_seconds=0.5):
    t = time.perf_counter()
    compiled = jax.jit(fn).lower(arg).compile()
    compile_s = time.perf_counter() - t
    jax.block_until_ready(compiled(arg))
    times = []
    # at least `repeats` calls and `min_seconds` (a few ms a call: 3 minima were noisy)
    while len(times) < repeats or (sum(times) < min_seconds and len(times) < 50):
        t = time.perf_counter()
        jax.block_until_ready(compiled(arg))
        times.append(time.perf_counter() - t)
    mem = compiled.memory_analysis()
    return {
        "seconds": min(times),
        "compile_s": compile_s,
        "temp_bytes": int(getattr(mem, "temp_size_in_bytes", -1)),
    }


def figure(rows, batches, horizons, method_name, platform):
    """Time and XLA temp memory of each variant, per batch size and horizon."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), constrained_layout=True)
    names = list(dict.fromkeys(r["variant"] for r in rows))
    for ax, key, label in (
        (axes[0], "time_ratio", "time / forward pass"),
        (axes[1], "temp_bytes", "XLA temp memory (bytes)"),
    ):
        combos = [(B, n) for B in batches for n in horizons]
        width = 0.8 / len(combos)
        for i, (B, n) in enumerate(combos):
            vals = [  # a variant not run at this size (a lease cut short) is left blank
                next(
                    (
                        r[key]
                        for r in rows
                        if r["variant"] == v and r["n_steps"] == n and r["batch"] == B
                    ),
                    float("nan"),
                )
                for v in names
            ]
            ax.bar(
                [j + width * i for j in range(len(names))],
                vals,
                width=width,
                label=f"B={B}, {n} steps",
            )
        ax.set_xticks(
            [j + 0.4 - width / 2 for j in range(len(names))],
            names,
            rotation=35,
            ha="right",
            fontsize=7,
        )
        if key == "time_ratio":
            ax.axhline(3, color="k", ls=":", lw=1, label="target 3x")
        ax.set_ylabel(label)
        ax.set_yscale("log")
        ax.legend(fontsize=8)
    fig.suptitle(f"derivatives of the mean tracking cost, {method_name}, {platform}")
    return fig


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", default=str(Path(__file__).parent / "results"))
    p.add_argument(
        "--method",
        type=method_by_name,
        default=None,
        help=f"one of {', '.join(METHODS)} (default RKMK4; --quick: LieEuler)",
    )
    p.add_argument("--batches", nargs="+", type=int, help="batch sizes (default 16 256)")
    p.add_argument("--horizons", nargs="+", type=int, help="step counts (default 1000 4000)")
    p.add_argument(
        "--cost",
        choices=("rollout", "trajectory"),
        default="rollout",
        help="rollout: expected_cost (the cost summed as the runs step); trajectory: a user's "
        "own cost on saved runs, the mean of tracking_cost(simulate(...)) (writes "
        "tune-trajectory.json; the forward pass, default reverse and jacfwd)",
    )
    p.add_argument(
        "--variants",
        nargs="+",
        choices=VARIANTS,
        help="variants to run besides the forward pass (default all)",
    )
    args = p.parse_args(argv)
    args.out = Path(args.out)
    args.out.mkdir(parents=True, exist_ok=True)
    # --quick is a smoke run: one horizon and the one-stage method, because
    # compiling the reverse passes is what takes the time.
    horizons, batches, repeats = ((100,), (2,), 3) if args.quick else ((1000, 4000), (16, 256), 3)
    horizons = tuple(args.horizons or horizons)
    batches = tuple(args.batches or batches)
    method_name = args.method or ("LieEuler" if args.quick else "RKMK4")
    method = METHODS[method_name]()
    scene = so3.scenes.seed()
    k = jnp.array([8.81, 2.54])
    rows = []
    bench = "tune" if args.cost == "rollout" else "tune-trajectory"
    for B, n in [(B, n) for B in batches for n in horizons]:
        R0, W0 = so3.initial_states(jax.random.key(0), B)

        def cost(k, ck="auto", program="auto", n=n, R0=R0, W0=W0):
            if args.cost == "trajectory":  # saves every state; ``ck`` does not apply
                return trajectory_cost(scene, k, R0, W0, method, n, program)
            return so3.expected_cost(
                scene, k[0], k[1], R0, W0, method, 1e-2, n, checkpoint_every=ck, program=program
            )

        variants = {
            "forward pass": lambda k: cost(k, None),
            "forward pass, array program": lambda k: cost(k, None, "array"),
            "reverse (default)": jax.grad(cost),
            "reverse, nine-number attitude tangents": nine_numbers(jax.grad(cost)),
            "reverse, checkpointed": jax.grad(lambda k: cost(k, program="autodiff")),
            "reverse, discrete adjoint": jax.grad(lambda k: cost(k, program="adjoint")),
            "reverse, no checkpoints": jax.grad(lambda k: cost(k, None, "autodiff")),
            "forward mode (jacfwd)": jax.jacfwd(lambda k: cost(k, None)),
            "forward mode, JAX's jvp": jax.jacfwd(lambda k: cost(k, None, "autodiff")),
            "Hessian (default)": jax.hessian(cost),
            "Hessian, autodiff": jax.hessian(lambda k: cost(k, program="autodiff")),
        }
        assert list(variants) == VARIANTS
        if args.cost == "trajectory":
            keep = ("forward pass", "reverse (default)", "forward mode (jacfwd)")
            variants = {k: v for k, v in variants.items() if k in keep}
        if args.variants:  # the forward pass stays: it is the baseline of the ratios
            variants = {k: v for k, v in variants.items() if k in args.variants or k == VARIANTS[0]}
        elif args.quick:  # the smoke run compiles the fewest programs
            variants.pop("forward pass, array program", None)
            variants.pop("reverse, no checkpoints", None)
            variants.pop("reverse, nine-number attitude tangents", None)
            variants.pop("reverse, checkpointed", None)
            variants.pop("forward mode, JAX's jvp", None)
            variants.pop("Hessian (default)", None)
            variants.pop("Hessian, autodiff", None)
        base = None
        for name, fn in variants.items():
            if isinstance(fn, nine_numbers):  # JAX caches derivatives of jitted programs
                jax.clear_caches()
            r = measure(fn, k, repeats)
            if isinstance(fn, nine_numbers):
                jax.clear_caches()
            base = base or r
            r.update(
                variant=name,
                method=method_name,
                n_steps=n,
                batch=B,
                time_ratio=r["seconds"] / base["seconds"],
                temp_ratio=r["temp_bytes"] / max(base["temp_bytes"], 1),
            )
            rows.append(r)
            C.write_partial(args, bench, rows)
            print(
                f"B={B:4d} n={n:5d} {name:28s} {r['seconds'] * 1e3:9.2f} ms "
                f"({r['time_ratio']:5.1f}x)  "
                f"temp {r['temp_bytes'] / 2**20:8.2f} MiB  compile {r['compile_s']:.1f} s"
            )
    json_path, png_path = C.output_paths(args, bench)
    C.write_json(
        json_path, {"benchmark": bench, "quick": args.quick, "env": C.environment(), "rows": rows}
    )
    platform = jax.devices()[0].platform
    fig = figure(rows, batches, horizons, method_name, platform)
    if args.cost == "trajectory":
        fig.suptitle(f"derivatives of a cost on saved runs, {method_name}, {platform}")
    C.save_figure(fig, png_path)


if __name__ == "__main__":
    main()
