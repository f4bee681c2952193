"""Array against scalarized program under ``vmap``, on whatever backend runs it.

The execution engine (`so3jax._engine.policy.batched_layout`) picks a layout per batch
size; the table was measured on the 2-core CPU (``gpu_layout`` holds what differs on
a GPU). This script runs the same calls with the engine's choice ("default") and
with the array program forced ("array": every entry of both tables set to never),
side by side in one process:

- throughput: ``vmap(simulate)`` over random starts of the seed scenario, 100
  steps of 0.01 s, body-steps per second, per method, batch and dtype;
- derivatives: the forward pass, ``jax.grad`` and ``jax.jacfwd`` (what `tune` takes
  by default for a few gains, ``gradient="auto"``) of the mean tracking cost (`expected_cost`,
  RKMK4, dt = 1e-2, 1000 steps) with respect to (k_R, k_Omega). These rows (``--check``,
  ``--derivatives``) set `GPU_LAYOUT["jacobian"]`: on a GPU the scalarized program runs
  faster per call but compiles several times longer, so it takes over only from the
  batch size where 100 calls with their compile take less time.

Writes ``results/layouts[-check][-<backend>][-quick].json`` (a ``.partial.json`` as it goes).

    python benchmarks/layouts.py            # GPU sizes (B up to 2^20)
    python benchmarks/layouts.py --quick    # smoke run: small batches
    python benchmarks/layouts.py --check    # only the rows around gpu_layout's cut (4096)
    python benchmarks/layouts.py --derivatives 4096   # only the derivative rows, at 4096 runs
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import _common as C  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import so3jax as s  # noqa: E402
from so3jax import _engine  # noqa: E402

#: The benchmarks' fixed-step methods (RKMK45 left out) and RKMK4 in Cayley coordinates.
METHODS = {k: v for k, v in C.lie_methods().items() if k != "RKMK45"}
METHODS["RKMK4-cayley"] = lambda: s.RKMK4(coords="cayley")


def layout(name):
    """``"default"``: the engine's tables; ``"array"``: the array program for every batch."""
    if name == "default":
        return C.engine_settings()
    active = _engine.policy.current()
    never = {
        table: {k: (None, None) for k, _ in getattr(active, table)}
        for table in ("batched_layout", "gpu_layout")
    }
    return C.engine_settings(**never)


def throughput_row(method, dtype, B, lay, repeats):
    scene = s.scenes.seed(dtype=dtype)
    R0s = s.random_rotation(jax.random.key(0), (B,), dtype=dtype)
    n = 100

    def fn(R0s):
        def one(R0):
            tr = s.simulate(scene, METHODS[method](), 0.01, n, n, R0=R0)
            return tr.R[-1], tr.Omega[-1]

        return jax.vmap(one)(R0s)

    with layout(lay):  # the layout is read while tracing
        r = C.compile_and_time(fn, R0s, repeats=repeats)
    return {
        "part": "throughput",
        "method": method,
        "dtype": jnp.dtype(dtype).name,
        "batch": B,
        "layout": lay,
        "run_s": r["run_s"],
        "compile_s": r["compile_s"],
        "body_steps_per_s": B * n / r["run_s"],
        "finite": bool(np.all(np.isfinite(np.asarray(r["out"][1])))),
    }


def derivative_rows(B, lay, repeats, n=1000):
    scene = s.scenes.seed()
    R0, W0 = s.initial_states(jax.random.key(0), B)
    k = jnp.array([8.81, 2.54])

    def cost(k, ck="auto"):
        return s.expected_cost(scene, k[0], k[1], R0, W0, s.RKMK4(), 1e-2, n, checkpoint_every=ck)

    rows = []
    forward = lambda k: cost(k, None)  # noqa: E731
    for what, fn in (
        ("forward pass", forward),
        ("grad", jax.grad(cost)),
        ("jacfwd", jax.jacfwd(forward)),
    ):
        with layout(lay):
            r = C.compile_and_time(fn, k, repeats=repeats)
        rows.append(
            {
                "part": "derivatives",
                "what": what,
                "batch": B,
                "n_steps": n,
                "layout": lay,
                "run_s": r["run_s"],
                "compile_s": r["compile_s"],
                "value": np.asarray(r["out"]).tolist(),
            }
        )
    return rows


def main():
    def extra(p):
        p.add_argument(
            "--check",
            action="store_true",
            help="only the rows around the GPU table's cut: RKMK4 at 2048 and 4096 runs, "
            "derivatives at 256",
        )
        p.add_argument(
            "--derivatives",
            nargs="+",
            type=int,
            metavar="B",
            help="only the derivative rows, at these batch sizes (written as layouts-derivatives)",
        )

    args = C.parse_args(__doc__.splitlines()[0], extra)
    name = "layouts-check" if args.check else "layouts"
    if args.derivatives:
        name, jobs, dbatches = "layouts-derivatives", [], args.derivatives
    elif args.check:
        jobs = [("RKMK4", "float32", 2048), ("RKMK4", "float32", 4096), ("RKMK4", "float64", 2048)]
        dbatches = [256]
        if args.quick:
            jobs, dbatches = [(m, d, B // 32) for m, d, B in jobs], [8]
    elif args.quick:
        jobs = [("RKMK4", "float32", 64), ("LGVI", "float32", 64)]
        dbatches = [64]
    else:
        big = 2**20
        jobs = [(m, "float32", big) for m in METHODS]
        jobs += [("RKMK4", "float32", 2048), ("RKMK4", "float32", 65536)]
        jobs += [("RKMK4", "float64", big), ("CF4", "float64", big), ("RKMK4", "float64", 2048)]
        dbatches = [256, 4096]
    rows = []
    for method, dtype, B in jobs:
        for lay in ("default", "array"):
            rows.append(throughput_row(method, dtype, B, lay, args.repeats))
            r = rows[-1]
            print(
                f"{method:13s} {dtype} B={B:8d} {lay:8s} {r['body_steps_per_s']:9.3g} body-steps/s"
                f"  run {r['run_s'] * 1e3:8.2f} ms  compile {r['compile_s']:5.1f} s",
                flush=True,
            )
            C.write_partial(args, name, rows)
    for B in dbatches:
        for lay in ("default", "array"):
            for r in derivative_rows(B, lay, args.repeats):
                rows.append(r)
                print(
                    f"{r['what']:13s} float64 B={B:8d} {lay:8s} run {r['run_s'] * 1e3:8.2f} ms"
                    f"  compile {r['compile_s']:5.1f} s",
                    flush=True,
                )
            C.write_partial(args, name, rows)
    json_path, _ = C.output_paths(args, name)
    C.write_json(json_path, {"env": C.environment(), "rows": rows})


if __name__ == "__main__":
    main()
