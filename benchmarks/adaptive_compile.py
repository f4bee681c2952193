"""Compile time of adaptive runs and their gradients: stages in a loop against unrolled.

The adaptive solvers (`so3jax.diffrax_solver` of `RKMK45`, `RKMKTsit5`, `RKMK32`) run
stages 1 .. s-1 of a step as one `fori_loop` (`rkmk_stages_looped`), so the vector
field is traced once a step; the alternative unrolls them in Python (`rkmk_stages`,
which the fixed-step methods use). This script measures both,
each in a fresh process (so no compiled program is shared), alternated over rounds:
the seed scenario over 10 s at ``rtol = atol = 1e-7``, `SaveAt` at two times,
`diffrax.RecursiveCheckpointAdjoint`:

- the forward run (``jit``, the final attitude): trace + compile, then run (min of 20);
- ``value_and_grad`` of a scalar of the final state in the gains (k_R, k_Omega):
  trace + compile, then run (min of 5).

A third variant, ``default``, runs the looped stages with ``adjoint=None``,
the library's default derivatives: through two gains the one-pass Jacobian
(`diffrax.ForwardMode`, the two unit tangents batched over one run) in place of
JAX's transpose through `diffrax.RecursiveCheckpointAdjoint`.

Writes ``results/adaptive-compile[-quick].json`` and ``.png``.

    python benchmarks/adaptive_compile.py            # 3 methods, 2 rounds (about 6 min)
    python benchmarks/adaptive_compile.py --quick    # RKMK32, forward runs only, 1 round
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import _common as C
import matplotlib.pyplot as plt
import numpy as np

METHODS = ("RKMKTsit5-cayley", "RKMK45", "RKMK32")
VARIANTS = ("unrolled", "looped", "default")


def child(variant: str, method: str, grads: bool) -> dict:
    """One measurement in this (fresh) process; the unrolled stages patched in."""
    import diffrax
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import so3jax as s
    from so3jax._integrators import _diffrax as D, _rkmk as RK

    if variant == "unrolled":

        def unrolled(tab, exact, scene, t, y, h, f0, coords="exp"):
            kw = dict(f0=f0, return_last=True, coords=coords)
            return RK.rkmk_stages(tab, exact, scene, t, y, h, **kw)

        D.rkmk_stages_looped = unrolled
    m = {"RKMKTsit5-cayley": s.RKMKTsit5(coords="cayley"), "RKMK45": s.RKMK45(),
         "RKMK32": s.RKMK32()}[method]  # fmt: skip
    base = s.scenes.seed()

    def run(gains):
        scene = eqx.tree_at(
            lambda sc: (sc.controller.gains.k_R, sc.controller.gains.k_Omega),
            base,
            (gains[0], gains[1]),
        )
        adjoint = None if variant == "default" else diffrax.RecursiveCheckpointAdjoint()
        return s.simulate(scene, m, t1=10.0, rtol=1e-7, atol=1e-7, saveat=2, max_steps=4096,
                          adjoint=adjoint)  # fmt: skip

    def loss(g):
        tr = run(g)
        return jnp.sum(tr.R[-1] ** 2 * jnp.arange(9.0).reshape(3, 3)) + jnp.sum(tr.Omega[-1])

    g0 = jnp.array(s.scenes.SEED_GAINS)

    def measure(fn, repeats):
        t = time.perf_counter()
        compiled = jax.jit(fn).lower(g0).compile()
        compile_s = time.perf_counter() - t
        run_s, out = C.time_call(compiled, g0, repeats=repeats)
        return compile_s, run_s, out

    row = {"method": method, "variant": variant}
    row["fwd_compile_s"], row["fwd_run_s"], R = measure(lambda g: run(g).R[-1], 20)
    row["final_R"] = np.asarray(R).tolist()
    if grads:
        row["grad_compile_s"], row["grad_run_s"], (_, g) = measure(jax.value_and_grad(loss), 5)
        row["grad"] = np.asarray(g).tolist()
    return row


TITLES = {
    "fwd_compile_s": "forward: trace + compile (s)",
    "grad_compile_s": "value_and_grad: trace + compile (s)",
    "fwd_run_s": "forward run (s)",
    "grad_run_s": "value_and_grad run (s)",
}


def figure(rows: list[dict]):
    """Bars per method: unrolled against looped stages, one panel per measured time."""
    keys = [k for k in TITLES if f"looped_{k}" in rows[0]]
    fig, axes = plt.subplots(1, len(keys), figsize=(3.4 * len(keys), 3.6), squeeze=False)
    x = np.arange(len(rows))
    for ax, k in zip(axes[0], keys, strict=True):
        for j, variant in enumerate(VARIANTS):
            ax.bar(x + (j - 1) * 0.27, [r[f"{variant}_{k}"] for r in rows], 0.27, label=variant)
        ax.set_xticks(x, [r["method"] for r in rows], rotation=20, fontsize=8)
        ax.set_title(TITLES[k], fontsize=9)
    axes[0][0].legend(fontsize=8)
    fig.suptitle(
        "Adaptive seed runs, 10 s, tol 1e-7: stages unrolled vs one loop "
        "(both RecursiveCheckpointAdjoint) vs the default derivatives",
        y=1.02,
    )
    fig.tight_layout()
    return fig


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        _, _, variant, method, grads = sys.argv
        print("ROW " + json.dumps(child(variant, method, grads == "1")))
        return

    def extra(p):
        p.add_argument("--rounds", type=int, default=None, help="alternations (default 2)")

    args = C.parse_args(__doc__.splitlines()[0], extra)
    methods = ("RKMK32",) if args.quick else METHODS
    rounds = args.rounds or (1 if args.quick else 2)
    grads = not args.quick
    best: dict[tuple, dict] = {}
    jobs = [(m, v) for _ in range(rounds) for m in methods for v in VARIANTS]
    for method, variant in C.progress(jobs, "processes"):
        cmd = [sys.executable, __file__, "--child", variant, method, "1" if grads else "0"]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
        row = json.loads(next(ln[4:] for ln in out.splitlines() if ln.startswith("ROW ")))
        old = best.get((method, variant))
        if old is not None:  # min over rounds, time by time
            for k, v in row.items():
                if k.endswith("_s"):
                    row[k] = min(v, old[k])
        best[(method, variant)] = row
    rows = []
    for method in methods:
        u, lp = best[(method, "unrolled")], best[(method, "looped")]
        d = best[(method, "default")]
        r = {"method": method}
        for k in ("fwd_compile_s", "fwd_run_s", "grad_compile_s", "grad_run_s"):
            if k in u:
                r[f"unrolled_{k}"], r[f"looped_{k}"], r[f"default_{k}"] = u[k], lp[k], d[k]
                r[f"{k}_ratio"] = u[k] / lp[k]  # > 1: the loop is faster
                r[f"{k}_default_ratio"] = lp[k] / d[k]  # > 1: the default is faster
        r["final_R_max_diff"] = float(np.abs(np.subtract(u["final_R"], lp["final_R"])).max())
        if grads:
            gu, gl, gd = np.asarray(u["grad"]), np.asarray(lp["grad"]), np.asarray(d["grad"])
            r["grad_rel_diff"] = float(np.abs(gu - gl).max() / np.abs(gu).max())
            r["default_grad_rel_diff"] = float(np.abs(gd - gl).max() / np.abs(gl).max())
        rows.append(r)
    cols = [c for c in rows[0] if c != "method"]
    C.print_table(rows, ["method", *cols], "unrolled / looped stages / default derivatives")
    json_path, png_path = C.output_paths(args, "adaptive-compile")
    C.write_json(json_path, {"benchmark": "adaptive-compile", "quick": args.quick,
                             "rounds": rounds, "env": C.environment(), "rows": rows})  # fmt: skip

    C.save_figure(figure(rows), png_path)


if __name__ == "__main__":
    main()
