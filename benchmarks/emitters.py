"""XLA's two CPU kernel emitters: compile and run time of the library's programs.

XLA's CPU compiler generates each fused kernel either with its MLIR "fusion
emitters" (the default since 2025) or with its older LLVM IR emitters
(``--xla_cpu_use_fusion_emitters=false``). This script compiles the same lowered
programs both ways in one process (``Lowered.compile(compiler_options=...)``, caches
cleared between compilations, the two settings alternated over ``--rounds``) and
reports, for each program and setting, the fastest compilation, the fastest run, and
the largest difference between the two settings' outputs relative to their size.

Programs (float64, seed scenario unless named; RKMK4):

- one run of 1000 steps (dt 1e-2), the array program;
- ``vmap(simulate)`` over 4096 starts, 750 steps (the scalarized program);
- ``expected_cost`` over B = 16 and 256 starts, 1000 steps: forward pass, ``grad`` and
  ``jacfwd`` in (k_R, k_Omega);
- DiffTune's quadrotor circle (control held 2.5 ms, 4000 steps): the loss, and its
  value and gradient in the 12 gains, reverse and forward mode.

The test suite runs with the older emitters (``tests/conftest.py``); a user sets the
same in ``XLA_FLAGS`` before JAX starts. This is a measurement of XLA, not a library
setting: ``import so3jax`` changes no global configuration.

Writes ``results/emitters[-quick].json`` and ``.png``.

    python benchmarks/emitters.py            # every program, 2 rounds
    python benchmarks/emitters.py --quick    # smoke run: Lie-Euler, tiny sizes, 1 round,
                                             # a run, a gradient and the quadrotor's loss
"""

from __future__ import annotations

import math
import time

import _common as C
import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import so3jax as so3

SETTINGS = {
    # Named explicitly, so that XLA_FLAGS (the test suite sets the other) cannot change it.
    "fusion emitters (XLA default)": {"xla_cpu_use_fusion_emitters": True},
    "older IR emitters": {"xla_cpu_use_fusion_emitters": False},
}


def programs(quick: bool):
    """(name, function, argument) for each program measured."""
    method = so3.LieEuler() if quick else so3.RKMK4()
    n_single, n_batch, batch = (50, 20, 8) if quick else (1000, 750, 4096)
    n_cost, cost_batches = (50, (2,)) if quick else (1000, (16, 256))
    n_quad = 40 if quick else 4000
    seed = so3.scenes.seed()
    k = jnp.array([8.81, 2.54])
    R0, _ = so3.initial_states(jax.random.key(1), batch)
    single = lambda r: so3.simulate(seed, method, 1e-2, n_single, R0=r).R[-1]
    out = [(f"seed, one run, {n_single} steps", single, R0[0])]

    def batched(R0):
        one = lambda r: so3.simulate(seed, method, 10 / n_batch, n_batch, R0=r, save_every=n_batch)
        return jax.vmap(lambda r: one(r).R[-1])(R0)

    if not quick:  # the smoke run compiles one program of each kind: a run, a gradient
        out.append((f"seed, vmap over {batch} starts, {n_batch} steps", batched, R0))
    for B in cost_batches:
        R0, W0 = so3.initial_states(jax.random.key(0), B)

        def cost(k, ck="auto", R0=R0, W0=W0):
            return so3.expected_cost(
                seed, k[0], k[1], R0, W0, method, 1e-2, n_cost, checkpoint_every=ck
            )

        forward = lambda k, c=cost: c(k, None)
        grad = (f"  grad, B = {B}", jax.grad(cost), k)
        out += [grad] if quick else [
            (f"expected_cost, B = {B}, {n_cost} steps", forward, k),
            grad,
            (f"  jacfwd, B = {B}", jax.jacfwd(forward), k),
        ]  # fmt: skip
    quad = so3.scenes.quadrotor_circle(control_period=0.0025)

    def loss(g):
        tr = so3.simulate(eqx.tree_at(lambda s: s.gains, quad, g), method, 0.0025, n_quad)
        return jnp.sum(tr.extras["e_x"] ** 2)

    out.append((f"quadrotor circle, {n_quad} steps", loss, quad.gains))
    if not quick:
        out.append(("  value and grad, 12 gains", jax.value_and_grad(loss), quad.gains))
        out.append(("  jacfwd, 12 gains", jax.jacfwd(loss), quad.gains))
    return out


def option_supported() -> bool:
    """Whether this jaxlib's XLA CPU compiler still takes the emitter option.

    (JAX 0.11's XLA has no ``xla_cpu_use_fusion_emitters``: it rejects the option.)
    """
    lowered = jax.jit(lambda x: x + 1).lower(jnp.zeros(2))
    try:
        lowered.compile(compiler_options=SETTINGS["older IR emitters"])
    except jax.errors.JaxRuntimeError as e:
        if "xla_cpu_use_fusion_emitters" in str(e):
            return False
        raise
    return True


def _rel_diff(a, b) -> float:
    a, b = jax.tree.leaves(a), jax.tree.leaves(b)
    worst = 0.0
    for x, y in zip(a, b, strict=True):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        scale = max(np.abs(y).max(), np.finfo(np.float64).tiny)
        worst = max(worst, float(np.abs(x - y).max() / scale))
    return worst


def main():
    def extra(p):
        p.add_argument("--rounds", type=int, default=None, help="alternations (default 2)")

    args = C.parse_args(__doc__.splitlines()[0], extra)
    rounds = args.rounds or (1 if args.quick else 2)
    if not option_supported():
        raise SystemExit(
            f"emitters.py: this jaxlib ({jax.__version__}) has no XLA CPU option "
            "'xla_cpu_use_fusion_emitters' (removed in newer XLA): nothing to compare."
        )
    rows = []
    for name, fn, arg in C.progress(programs(args.quick), "programs"):
        best = {s: {"compile_s": math.inf, "run_s": math.inf} for s in SETTINGS}
        outs = {}
        for _ in range(rounds):
            for setting, options in SETTINGS.items():
                jax.clear_caches()  # otherwise the second compilation is a cache hit
                lowered = jax.jit(fn).lower(arg)
                t = time.perf_counter()
                compiled = lowered.compile(compiler_options=options)
                compile_s = time.perf_counter() - t
                run_s, outs[setting] = C.time_call(compiled, arg, repeats=args.repeats)
                b = best[setting]
                b["compile_s"] = min(b["compile_s"], compile_s)
                b["run_s"] = min(b["run_s"], run_s)
        default, older = (best[s] for s in SETTINGS)
        row = {
            "program": name.strip(),
            "default_compile_s": default["compile_s"],
            "default_run_s": default["run_s"],
            "older_compile_s": older["compile_s"],
            "older_run_s": older["run_s"],
            "compile_speedup": default["compile_s"] / older["compile_s"],
            "run_speedup": default["run_s"] / older["run_s"],
            "max_rel_diff": _rel_diff(*(outs[s] for s in SETTINGS)),
        }
        rows.append(row)
        print(
            f"{name:45s} compile {row['default_compile_s']:6.2f} -> {row['older_compile_s']:6.2f} s"
            f" ({row['compile_speedup']:.2f}x)  run {row['default_run_s'] * 1e3:9.3f} -> "
            f"{row['older_run_s'] * 1e3:9.3f} ms ({row['run_speedup']:.2f}x)  "
            f"diff {row['max_rel_diff']:.1e}"
        )
        # The outputs agree to round-off; a larger difference is a wrong program.
        assert row["max_rel_diff"] < 1e-9, (name, row["max_rel_diff"])
    json_path, png_path = C.output_paths(args, "emitters")
    C.write_json(
        json_path,
        {
            "benchmark": "emitters",
            "quick": args.quick,
            "rounds": rounds,
            "repeats": args.repeats,
            "settings": SETTINGS,
            "env": C.environment(),
            "rows": rows,
        },
    )
    fig, ax = plt.subplots(figsize=(9, 0.45 * len(rows) + 1.2), constrained_layout=True)
    y = np.arange(len(rows))
    ax.barh(y - 0.2, [r["compile_speedup"] for r in rows], 0.4, label="compile")
    ax.barh(y + 0.2, [r["run_speedup"] for r in rows], 0.4, label="run")
    ax.axvline(1, color="k", lw=1)
    ax.set_yticks(y, [r["program"] for r in rows], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("speed-up of the older IR emitters over XLA's default (time ratio)")
    ax.legend(fontsize=8)
    ax.set_title(f"XLA CPU kernel emitters, {C.environment()['device_kind']}", fontsize=9)
    C.save_figure(fig, png_path)


if __name__ == "__main__":
    main()
