"""Cost of one gradient of the tracking cost relative to one forward pass.

The mean tracking cost of the seed scenario over B random initial attitudes
(RKMK4, dt = 1e-2), as a function of (k_R, k_Omega): forward pass, reverse
mode with checkpointed blocks (`rollout_cost`'s default, memory ~ sqrt(n)),
reverse mode without checkpoints (memory ~ n) and forward mode (`jax.jacfwd`,
2 tangents). For each: run time (min over repeats, compiled), compile time,
and XLA's temp memory (`compiled.memory_analysis()`), at two horizons; ratios
are against the forward pass measured in the same run. Target: a gradient
under 4x a forward pass.

Writes ``results/tune[-quick].json`` and ``.png``.

    python benchmarks/tune.py            # 10 s and 40 s horizons, B = 16
    python benchmarks/tune.py --quick    # smoke run: 1 s, B = 2, LieEuler
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
from so3jax._integrators import METHODS, method_by_name  # noqa: E402


def measure(fn, arg, repeats):
    t = time.perf_counter()
    compiled = jax.jit(fn).lower(arg).compile()
    compile_s = time.perf_counter() - t
    jax.block_until_ready(compiled(arg))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(compiled(arg))
        times.append(time.perf_counter() - t)
    mem = compiled.memory_analysis()
    return {
        "seconds": min(times),
        "compile_s": compile_s,
        "temp_bytes": int(getattr(mem, "temp_size_in_bytes", -1)),
    }


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
    args = p.parse_args(argv)
    # --quick is a smoke run: one horizon and the one-stage method, because
    # compiling the reverse passes is what takes the time.
    horizons, B, repeats = ((100,), 2, 3) if args.quick else ((1000, 4000), 16, 5)
    method_name = args.method or ("LieEuler" if args.quick else "RKMK4")
    method = METHODS[method_name]()
    scene = so3.scenes.seed()
    R0, W0 = so3.initial_states(jax.random.key(0), B)
    k = jnp.array([8.81, 2.54])
    rows = []
    for n in horizons:

        def cost(k, ck="auto"):
            return so3.expected_cost(
                scene, k[0], k[1], R0, W0, method, 1e-2, n, checkpoint_every=ck
            )

        variants = {
            "forward pass": lambda k: cost(k, None),
            "reverse, checkpointed": jax.grad(cost),
            "reverse, no checkpoints": jax.grad(lambda k: cost(k, None)),
            "forward mode (jacfwd)": jax.jacfwd(lambda k: cost(k, None)),
        }
        base = None
        for name, fn in variants.items():
            r = measure(fn, k, repeats)
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
            print(
                f"n={n:5d} {name:24s} {r['seconds'] * 1e3:9.2f} ms ({r['time_ratio']:5.1f}x)  "
                f"temp {r['temp_bytes'] / 2**20:8.2f} MiB  compile {r['compile_s']:.1f} s"
            )
    args.out = Path(args.out)
    args.out.mkdir(parents=True, exist_ok=True)
    json_path, png_path = C.output_paths(args, "tune")
    C.write_json(
        json_path, {"benchmark": "tune", "quick": args.quick, "env": C.environment(), "rows": rows}
    )
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), constrained_layout=True)
    names = list(dict.fromkeys(r["variant"] for r in rows))
    for ax, key, label in (
        (axes[0], "time_ratio", "time / forward pass"),
        (axes[1], "temp_bytes", "XLA temp memory (bytes)"),
    ):
        for i, n in enumerate(horizons):
            vals = [
                next(r[key] for r in rows if r["variant"] == v and r["n_steps"] == n) for v in names
            ]
            ax.bar([j + 0.4 * i for j in range(len(names))], vals, width=0.4, label=f"{n} steps")
        ax.set_xticks([j + 0.2 for j in range(len(names))], names, rotation=15, fontsize=8)
        ax.set_ylabel(label)
        ax.set_yscale("log")
        ax.legend(fontsize=8)
    fig.suptitle(
        f"gradient of the mean tracking cost, {method_name}, B = {B}, {jax.devices()[0].platform}"
    )
    C.save_figure(fig, png_path)


if __name__ == "__main__":
    main()
