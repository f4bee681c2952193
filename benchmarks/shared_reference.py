"""What sharing the reference attitude Rd saves in a batch (issue 11).

The seed scenario integrates the reference attitude ``Rd`` next to the body's
``R``. Every run of a gain sweep, or of a batch of starts, has the same
``Rd(t)``. A tracking scene declares it time-driven
(``Scene.time_driven_groups = (1,)``), so the scalarized batch program keeps
it unbatched and integrates it once per batch. Each batch below runs twice in
the same process: with the seed scene as it is ("shared"), and with a copy of
the scene that does not declare ``Rd`` time-driven ("per run", what every
batch did before). The arithmetic is otherwise the same, so the ratio isolates
the sharing:

- ``vmap(simulate)`` over ``B`` gain pairs from one start (RKMK4, dt 0.01);
- `so3jax.expected_cost` over ``B`` random starts. It hands the start to the
  engine apart from the scene's attitudes, which keeps ``Rd0`` unbatched.

Writes ``results/shared_reference[-quick].json`` and ``.png``.

    python benchmarks/shared_reference.py            # B = 2048 and 256, 1000 steps
    python benchmarks/shared_reference.py --quick    # B = 8, 20 steps
"""

from __future__ import annotations

from typing import ClassVar

import _common as C
import jax
import jax.numpy as jnp
import numpy as np

import so3jax as s
from so3jax._tune import with_gains
from so3jax.scenes import Tracking


class PerRun(Tracking):
    """The tracking scene without ``Rd`` declared time-driven: every run integrates it."""

    time_driven_groups: ClassVar[tuple[int, ...]] = ()


def per_run(scene: Tracking) -> PerRun:
    return PerRun(
        body=scene.body, controller=scene.controller, reference=scene.reference, y0=scene.y0
    )


def main():
    args = C.parse_args(__doc__.splitlines()[0])
    n_steps, B_gains, B_starts = (20, 8, 8) if args.quick else (1000, 2048, 256)
    repeats = args.repeats or (1 if args.quick else 5)
    dt, method = 0.01, s.RKMK4()
    seed = s.scenes.seed()
    scenes = {"shared": seed, "per run": per_run(seed)}
    k_R = jnp.linspace(2.0, 20.0, B_gains)
    k_Omega = jnp.linspace(1.0, 5.0, B_gains)
    R0, W0 = s.initial_states(0, B_starts)
    k = jnp.array([8.81, 2.54])
    rows, outs = [], {}
    for name, scene in scenes.items():

        def gains(kr, ko, scene=scene):
            tr = s.simulate(with_gains(scene, kr, ko), method, dt, n_steps, save_every=n_steps)
            return tr.R[-1]

        def starts(k, scene=scene):
            return s.expected_cost(scene, k[0], k[1], R0, W0, method, dt, n_steps)

        for batch, fn, fargs, B in (
            ("vmap(simulate) over gain pairs", jax.vmap(gains), (k_R, k_Omega), B_gains),
            ("expected_cost over starts", starts, (k,), B_starts),
        ):
            r = C.compile_and_time(fn, *fargs, repeats=repeats)
            outs[(name, batch)] = np.asarray(r["out"])
            rows.append(
                {
                    "batch": batch,
                    "Rd": name,
                    "B": B,
                    "n_steps": n_steps,
                    "run_s": r["run_s"],
                    "compile_s": r["compile_s"],
                    "body_steps_per_s": B * n_steps / r["run_s"],
                }
            )
    for row in rows:
        base = next(r for r in rows if r["batch"] == row["batch"] and r["Rd"] == "per run")
        row["speedup"] = base["run_s"] / row["run_s"]
        same = outs[(row["Rd"], row["batch"])], outs[("per run", row["batch"])]
        row["max_diff_vs_per_run"] = float(np.max(np.abs(same[0] - same[1])))
    C.print_table(
        rows,
        ["batch", "Rd", "B", "run_s", "body_steps_per_s", "speedup", "compile_s"],
        f"RKMK4, {n_steps} steps of {dt} s, float64",
    )
    fig, ax = C.plt.subplots(figsize=(6.5, 3.4), constrained_layout=True)
    batches = list(dict.fromkeys(r["batch"] for r in rows))
    for i, name in enumerate(scenes):
        vals = [next(r for r in rows if r["batch"] == b and r["Rd"] == name) for b in batches]
        x = np.arange(len(batches)) + (i - 0.5) * 0.38
        ax.bar(x, [v["body_steps_per_s"] for v in vals], 0.38, label=f"Rd {name}")
        for xi, v in zip(x, vals, strict=True):
            if name == "shared":
                xy = (xi, v["body_steps_per_s"])
                ax.annotate(f"{v['speedup']:.2f}x", xy, ha="center", va="bottom", fontsize=8)
    sizes = [next(r["B"] for r in rows if r["batch"] == b) for b in batches]
    ticks = [f"{b}\n(B = {n})" for b, n in zip(batches, sizes, strict=True)]
    ax.set_xticks(np.arange(len(batches)), ticks)
    ax.set_ylabel("body-steps / s")
    ax.set_title(f"Sharing the reference attitude (RKMK4, {n_steps} steps)")
    ax.legend()
    json_path, png_path = C.output_paths(args, "shared_reference")
    C.save_figure(fig, png_path)
    C.write_json(json_path, {"env": C.environment(), "method": "RKMK4", "dt": dt, "rows": rows})


if __name__ == "__main__":
    main()
