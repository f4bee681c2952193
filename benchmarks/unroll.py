"""Unrolled step loops (`lax.scan`'s ``unroll``) under ``vmap``, on whatever backend runs it.

On a GPU a batched run of a few thousand trajectories is latency bound: each
iteration of the step loop costs tens of microseconds whatever the batch (an
H100 at 2048 to 4096 runs). Unrolling the loop runs
``u`` steps per iteration. the engine policy's ``scan_unroll`` sets it at trace time;
this script sets it per row (clearing JAX's caches around each, as the layout
is), side by side in one process:

- equal accuracy: 4096 runs of the seed for 10 s at final attitude error 1e-8
  (float64; step counts and Tsit5's tolerance from ``--calibration``, default
  ``results/throughput.json``), RKMK4 (default program) and RKMKTsit5 in Cayley
  coordinates against vmapped diffrax Tsit5;
- throughput: ``vmap(simulate)`` of RKMK4 (default program), 100 steps from
  random starts, float32, body-steps per second;
- derivatives: ``jax.grad`` and the forward pass of the mean tracking cost
  (``expected_cost``, RKMK4, 1000 steps, B = 256).

Compile times are reported with every row: unrolling multiplies the loop body.
Writes ``results/unroll[-<backend>][-quick].json`` (a ``.partial.json`` as it goes).

    python benchmarks/unroll.py                 # GPU sizes
    python benchmarks/unroll.py --quick         # smoke run: small batches
"""

from __future__ import annotations

from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import _common as C  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import throughput as T  # noqa: E402
from layouts import layout  # noqa: E402

import so3jax as s  # noqa: E402


def unrolled(u):
    """Trace the engine's step loops with ``unroll=u`` (JAX's caches cleared around it)."""
    return C.engine_settings(scan_unroll=u)


def row(part, what, batch, u, r, **extra):
    """One result row: what was run, at which unroll, its run and compile time."""
    return dict(part=part, what=what, batch=batch, unroll=u, run_s=r["run_s"],
                compile_s=r["compile_s"], **extra)  # fmt: skip


def timed(fn, x, u, repeats, lay="default"):
    with layout(lay), unrolled(u):
        return C.compile_and_time(fn, x, repeats=repeats)


def main():
    def extra(p):
        p.add_argument("--unroll", type=int, nargs="+", default=[1, 2, 5, 10])
        p.add_argument("--parts", nargs="+", default=["equal", "throughput", "derivatives"])
        p.add_argument("--batches", type=int, nargs="+", default=[2048, 2**20])
        p.add_argument(
            "--calibration",
            default=str(Path(__file__).parent / "results" / "throughput.json"),
            help="the JSON whose equal-accuracy settings (step counts, Tsit5 tol) to take",
        )

    args = C.parse_args(__doc__.splitlines()[0], extra)
    reps = args.repeats
    rows = []

    def record(e):
        rows.append(e)
        extra = f"  {e['body_steps_per_s']:9.3g} body-steps/s" if "body_steps_per_s" in e else ""
        print(
            f"{e['part']:11s} {e['what']:28s} B={e['batch']:8d} unroll {e['unroll']:3d}"
            f"  run {e['run_s'] * 1e3:9.3f} ms  compile {e['compile_s']:6.2f} s{extra}",
            flush=True,
        )
        C.write_partial(args, "unroll", rows)

    if "equal" in args.parts:
        scene = T.base_scene(jnp.float64)
        cal = T.calibrate(scene, args.quick, None if args.quick else args.calibration)
        B = 64 if args.quick else 4096
        R0s = s.random_rotation(jax.random.key(1), (B,), dtype=jnp.float64)
        fn = T.runner("diffrax Tsit5", scene, None, 0, t1=cal["T"], tol=cal["tsit5_tol"])
        r = timed(fn, R0s, 1, min(reps, 3))
        tsit5 = r["run_s"]
        record(row("equal", "diffrax Tsit5", B, 1, r, speedup_over_tsit5=1.0))
        labels = (
            ["RKMK4 default"] if args.quick else ["RKMK4 default", "RKMKTsit5-cayley scalarized"]
        )
        for label in labels:
            n = cal["n_steps"][label.split(" ")[0]]
            fn = T.runner(label, scene, cal["T"] / n, n)
            for u in args.unroll:
                r = timed(fn, R0s, u, min(reps, 3))
                record(
                    row("equal", label, B, u, r, n_steps=n, us_per_step=r["run_s"] / n * 1e6,
                        speedup_over_tsit5=tsit5 / r["run_s"])
                )  # fmt: skip

    if "throughput" in args.parts:
        n = 20 if args.quick else 100
        batches = [64] if args.quick else args.batches
        scene = s.scenes.seed(dtype=jnp.float32)
        for B in batches:
            R0s = s.random_rotation(jax.random.key(0), (B,), dtype=jnp.float32)
            # "RKMK4 default": the engine's choice ("RKMK4" in `T.VARIANTS` is the array
            # program, which would run under both settings).
            fn = T.runner("RKMK4 default", scene, 0.01, n)
            # The array program (vmapped) at the smaller batches: it compiles in a fraction
            # of the scalarized program's time, and at a few thousand runs a GPU runs it
            # about as fast as the default.
            for lay in ("default", "array") if B <= 65536 else ("default",):
                for u in args.unroll:
                    r = timed(fn, R0s, u, reps, lay)
                    finite = bool(np.all(np.isfinite(np.asarray(r["out"][1]))))
                    record(
                        row("throughput", f"RKMK4 float32 {lay}", B, u, r, layout=lay,
                            body_steps_per_s=B * n / r["run_s"], finite=finite)
                    )  # fmt: skip

    if "derivatives" in args.parts:
        n = 100 if args.quick else 1000
        B = 16 if args.quick else 256
        scene = s.scenes.seed()
        R0, W0 = s.initial_states(jax.random.key(0), B)
        k = jnp.array([8.81, 2.54])

        def cost(k, ck="auto"):
            return s.expected_cost(
                scene, k[0], k[1], R0, W0, s.RKMK4(), 1e-2, n, checkpoint_every=ck
            )

        for what, fn in (("forward pass", lambda k: cost(k, None)), ("grad", jax.grad(cost))):
            for u in args.unroll:
                r = timed(fn, k, u, reps)
                value = np.asarray(r["out"]).tolist()
                record(row("derivatives", what, B, u, r, n_steps=n, value=value))

    json_path, _ = C.output_paths(args, "unroll")
    C.write_json(json_path, {"env": C.environment(), "rows": rows})


if __name__ == "__main__":
    main()
