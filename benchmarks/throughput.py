"""Batched throughput: body-steps per second against batch size, and at equal accuracy.

1. *Sweep*: the seed scenario from random initial attitudes, ``n_steps``
   steps of 0.01 s, vmapped over the batch, for every Lie-group method and
   diffrax (fixed-step RK4 and adaptive Tsit5, ambient), in float64 and
   float32: body-steps per second (batch x steps / wall time; for adaptive
   Tsit5, the accepted steps), compile time and XLA's memory estimate
   (arguments + outputs + temporaries). Batch 1 to 65536 (``--quick``: 8). A
   method's name is its default program; ``"RKMK4 array"`` forces the array
   program and ``"RKMK4 scalarized"`` (and the other variants below) the
   scalarized one.
2. *Equal accuracy*: 4096 seed trajectories (``--quick``: 64, RKMK4 only) of 10 s, each
   method at the step count (diffrax Tsit5: the tolerance) that reaches final
   attitude error 1e-8 on the seed initial condition (calibrated in the same
   run): trajectories per second and the ratio to vmapped diffrax Tsit5. The
   Lie-group methods run with default settings ("RKMK4 default": the execution
   engine runs a vmapped batch as the scalarized program), forced to the array
   program ("RKMK4", ``scalarize=False``) and forced scalarized
   (``scalarize=True``: structure of arrays under vmap), in exponential and
   Cayley coordinates.

The JSON records `jax.default_backend()` and the device kind: run it on a GPU
for the GPU column (``benchmarks/gpu.sh`` does, sized for a device lease, with
``--dtypes``, ``--sweep-only``, ``--variants`` and ``--calibration``, which takes
the step counts and tolerance of an earlier run's JSON). ``--cpu-devices N`` splits
the CPU into N JAX devices and shards every batch across them (the Lie-group runs
and the diffrax baseline alike).

Writes ``results/throughput[-<backend>][-quick].json`` and ``.png`` (the backend
named off CPU), and ``.partial.json`` after every sweep row.

    python benchmarks/throughput.py            # full (several minutes)
    python benchmarks/throughput.py --quick    # seconds
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import jax

# ``--cpu-devices N``: N CPU devices, set before any backend starts (a process-wide setting,
# which the library itself never makes); every batch is then sharded across them.
if "--cpu-devices" in sys.argv:
    jax.config.update("jax_num_cpu_devices", int(sys.argv[sys.argv.index("--cpu-devices") + 1]))

import _common as C  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh, NamedSharding, PartitionSpec  # noqa: E402

import so3jax as s  # noqa: E402

LIE = C.lie_methods()
AMBIENT = ["diffrax RK4", "diffrax Tsit5"]
TSIT5_TOL = {"float64": 1e-8, "float32": 1e-5}


def shard(x):
    """``x`` split along its batch axis across the local devices (as is with one device)."""
    devices = jax.local_devices()
    if len(devices) == 1 or x.shape[0] % len(devices):
        return x
    return jax.device_put(x, NamedSharding(Mesh(devices, ("batch",)), PartitionSpec("batch")))


def base_scene(dtype):
    if hasattr(s.scenes, "seed"):
        return s.scenes.seed(dtype=dtype)
    return s.scenes.free_body(
        jnp.array([1.0, 2.0, 3.0], dtype),
        jnp.eye(3, dtype=dtype),
        jnp.array([0.5, 1.0, -0.3], dtype),
    )


def with_R0(scene, R0):
    """The scene started from ``R0`` (for the diffrax baseline, which takes a scene)."""
    return eqx.tree_at(lambda sc: sc.y0.R, scene, scene.y0.R.at[0].set(R0))


#: Equal-accuracy variants: label -> (method factory, scalarize). ``None`` is the
#: default (the execution engine picks the scalarized program under vmap);
#: ``False`` forces the array program, ``True`` the scalarized one.
VARIANTS = {
    "RKMK4 default": (s.RKMK4, None),
    "RKMK4": (s.RKMK4, False),
    "RKMK4 scalarized": (s.RKMK4, True),
    "RKMK4-cayley scalarized": (lambda: s.RKMK4(coords="cayley"), True),
    "RKMK45-cayley scalarized": (lambda: s.RKMK45(coords="cayley"), True),
    "RKMKTsit5-cayley scalarized": (lambda: s.RKMKTsit5(coords="cayley"), True),
}


#: Extra sweep labels: the array program forced (``scalarize=False``). In the sweep a
#: method's plain name (``"RKMK4"``) is the default program.
SWEEP_VARIANTS = {"RKMK4 array": (s.RKMK4, False)}
#: The labels the sweep looks up before the method names (none of them a method's name).
SWEEP_LABELS = {k: v for k, v in {**VARIANTS, **SWEEP_VARIANTS}.items() if k not in LIE}


def runner(label, scene, dt, n_steps, t1=None, tol=None, variants=VARIANTS):
    """``f(R0s) -> (R_final, Omega_final, steps)``, vmapped over initial attitudes.

    ``label`` is looked up in ``variants`` first (the equal-accuracy labels, where
    ``"RKMK4"`` is the array program), then among the methods (default program).
    """

    def one(R0):
        # The Lie-group runs take the start as simulate's R0 (what the docs show for a
        # batch of starts): the reference attitude Rd then stays unbatched, integrated
        # once per batch. The ambient baseline integrates it once per run.
        if label in variants:
            make, scal = variants[label]
            tr = s.simulate(scene, make(), dt, n_steps, n_steps, scalarize=scal, R0=R0)
            steps = jnp.asarray(n_steps)
        elif label in LIE:
            tr = s.simulate(scene, LIE[label](), dt, n_steps, save_every=n_steps, R0=R0)
            steps = jnp.asarray(n_steps)
        elif label == "diffrax RK4":
            sc = with_R0(scene, R0)  # the ambient baseline takes the start in its scene
            tr = s.simulate_ambient(sc, "rk4", dt=dt, n_steps=n_steps, save_every=n_steps)
            steps = tr.extras["num_accepted_steps"]
        else:
            T = n_steps * dt if t1 is None else t1
            sc = with_R0(scene, R0)
            tr = s.simulate_ambient(sc, "tsit5", T, rtol=tol, atol=tol, n_save=2)
            steps = tr.extras["num_accepted_steps"]
        return tr.R[-1], tr.Omega[-1], steps

    return jax.vmap(one)


def sweep(args, name="throughput"):
    """Body-steps/s per dtype, method and batch; rows also to ``<name>.partial.json``."""
    n_steps = 20 if args.quick else 100
    dt = 0.01
    batches = [8] if args.quick else [1, 16, 256, 4096, 65536]
    labels = ["RKMK4", "diffrax RK4"] if args.quick else list(LIE) + AMBIENT
    batches = args.batches or batches
    labels = args.methods or labels
    dtypes = args.dtypes
    rows = []
    jobs = [(d, m, b) for d in dtypes for m in labels for b in batches]
    for dname, label, B in C.progress(jobs, "throughput"):
        dtype = jnp.dtype(dname)
        scene = base_scene(dtype)
        R0s = shard(s.random_rotation(jax.random.key(0), (B,), dtype=dtype))
        fn = runner(label, scene, dt, n_steps, tol=TSIT5_TOL[dname], variants=SWEEP_LABELS)
        reps = args.repeats if B * n_steps <= 1e6 else max(1, min(args.repeats, 2))
        r = C.compile_and_time(fn, R0s, repeats=reps)
        steps = float(np.sum(np.asarray(r["out"][2])))
        finite = bool(np.all(np.isfinite(np.asarray(r["out"][1]))))
        rows.append(
            {
                "dtype": dname,
                "method": label,
                "batch": B,
                "run_s": r["run_s"],
                "compile_s": r["compile_s"],
                "body_steps_per_s": steps / r["run_s"],
                "memory_mb": None if r["memory_bytes"] is None else r["memory_bytes"] / 2**20,
                "finite": finite,
            }
        )
        C.write_partial(args, name, rows)
    return {"n_steps": n_steps, "dt": dt, "batches": batches, "methods": labels, "rows": rows}


def _n_star(scene, ref, T, make, ns):
    """The step count (rounded up to 25) where ``make()`` reaches attitude error 1e-8."""
    errs = []
    for n in ns:
        R = s.simulate(scene, make(), T / n, n, save_every=n).R[-1]
        errs.append(float(s.geodesic_distance(R, ref)))
    n_star = C.interp_loglog(errs, ns, 1e-8)
    return ns[-1] if not math.isfinite(n_star) else int(math.ceil(n_star / 25) * 25)


def calibrate(scene, quick, source=None):
    """Step counts and the Tsit5 tolerance reaching final attitude error 1e-8 (10 s).

    ``--quick`` skips the search (fixed settings; their errors are still measured).
    ``source`` (``--calibration PATH``): the settings of an earlier run's JSON, taken
    as they are (errors included): the search is a property of the method, not of the
    device, and costs dozens of compilations.
    """
    if source is not None:
        old = json.loads(Path(source).read_text())["equal_accuracy"]
        keys = ["T", "rkmk4_n_steps", "rkmk4_err", "n_steps", "errors", "tsit5_tol", "tsit5_err"]
        return {**{k: old[k] for k in keys}, "calibration_from": Path(source).name}
    T = 10.0
    if quick:  # a smoke run: RKMK4 only, against itself at 4x the steps
        ref = s.simulate(scene, s.RKMK4(), T / 4000, 4000, save_every=4000).R[-1]
        return _check_settings(scene, ref, T, {"RKMK4": 1000}, 1e-9)
    n_ref = 40000
    ref = s.simulate(scene, s.RKMK45(), T / n_ref, n_ref, save_every=n_ref).R[-1]
    n_star = {
        "RKMK4": _n_star(scene, ref, T, s.RKMK4, [500, 700, 1000, 1400]),
        "RKMK4-cayley": _n_star(
            scene, ref, T, lambda: s.RKMK4(coords="cayley"), [500, 700, 1000, 1400]
        ),
        "RKMK45-cayley": _n_star(
            scene, ref, T, lambda: s.RKMK45(coords="cayley"), [200, 250, 300, 400, 500]
        ),
        "RKMKTsit5-cayley": _n_star(
            scene, ref, T, lambda: s.RKMKTsit5(coords="cayley"), [200, 250, 300, 400, 500]
        ),
    }
    tols = [1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11]
    terrs = []
    for tol in tols:
        tr = s.simulate_ambient(scene, "tsit5", T, rtol=tol, atol=tol, n_save=2)
        terrs.append(float(s.geodesic_distance(s.project(tr.R[-1]), ref)))
    tol_star = C.interp_loglog(terrs, tols, 1e-8)
    tol_star = tols[-1] if not math.isfinite(tol_star) else tol_star
    return _check_settings(scene, ref, T, n_star, tol_star)


def _check_settings(scene, ref, T, n_star, tol_star):
    """Final attitude errors of the chosen settings on the seed initial condition."""
    if len(n_star) > 1:
        n_star.setdefault("RKMK4-cayley", n_star["RKMK4"])
    errs = {}
    for name, n in n_star.items():
        make = VARIANTS[name.replace("-cayley", "-cayley scalarized")][0]
        R = s.simulate(scene, make(), T / n, n, save_every=n).R[-1]
        errs[name] = float(s.geodesic_distance(R, ref))
    tr = s.simulate_ambient(scene, "tsit5", T, rtol=tol_star, atol=tol_star, n_save=2)
    return {
        "T": T,
        "rkmk4_n_steps": n_star["RKMK4"],
        "rkmk4_err": errs["RKMK4"],
        "n_steps": n_star,
        "errors": errs,
        "tsit5_tol": tol_star,
        "tsit5_err": float(s.geodesic_distance(s.project(tr.R[-1]), ref)),
    }


def equal_accuracy(args):
    scene = base_scene(jnp.float64)
    cal = calibrate(scene, args.quick, args.calibration)
    B = 64 if args.quick else 4096
    T = cal["T"]
    R0s = shard(s.random_rotation(jax.random.key(1), (B,), dtype=jnp.float64))
    # --quick: the array program only (each scalarized variant compiles for seconds).
    variants = ["RKMK4"] if args.quick else list(VARIANTS)
    variants = args.variants or variants
    if "RKMK4" not in variants:  # the speed-up row reads it
        variants = ["RKMK4", *variants]
    out = {"batch": B, "variants": variants, "devices": len(jax.local_devices()), **cal}
    runs = []
    for label in variants:
        n = cal["n_steps"][label.split(" ")[0]]
        runs.append((label, runner(label, scene, T / n, n)))
    runs.append(
        ("diffrax Tsit5", runner("diffrax Tsit5", scene, None, 0, t1=T, tol=cal["tsit5_tol"]))
    )
    for label, fn in C.progress(runs, "equal accuracy"):
        r = C.compile_and_time(fn, R0s, repeats=max(1, min(args.repeats, 3)))
        steps = float(np.sum(np.asarray(r["out"][2])))
        out[label] = {
            "run_s": r["run_s"],
            "compile_s": r["compile_s"],
            "trajectories_per_s": B / r["run_s"],
            "body_steps_per_s": steps / r["run_s"],
            "mean_steps": steps / B,
            "memory_mb": None if r["memory_bytes"] is None else r["memory_bytes"] / 2**20,
        }
    out["speedup_rkmk4_over_tsit5"] = out["diffrax Tsit5"]["run_s"] / out["RKMK4"]["run_s"]
    out["speedup_over_tsit5"] = {
        k: out["diffrax Tsit5"]["run_s"] / out[k]["run_s"] for k in variants
    }
    best = max(variants, key=lambda k: out["speedup_over_tsit5"][k])
    out["best"] = {"method": best, "speedup_over_tsit5": out["speedup_over_tsit5"][best]}
    return out


def plot(res, path):
    sw = res["sweep"]
    eq = res.get("equal_accuracy")
    fig, axes = C.plt.subplots(1, 3 if eq else 2, figsize=(17 if eq else 11.5, 4.8))
    for ax, dname in zip(axes[:2], ["float64", "float32"], strict=True):
        if not any(r["dtype"] == dname for r in sw["rows"]):
            ax.set_axis_off()
            continue
        for label in dict.fromkeys(r["method"] for r in sw["rows"]):
            rr = [r for r in sw["rows"] if r["method"] == label and r["dtype"] == dname]
            ax.loglog(
                [r["batch"] for r in rr],
                [r["body_steps_per_s"] for r in rr],
                "--s" if "diffrax" in label else "-o",
                label=label,
                ms=4,
            )
        ax.set_xlabel("batch size")
        ax.set_ylabel("body-steps / s")
        where = f"{res['env']['backend']} ({res['env']['device_kind']})"
        if "from" in sw:  # an --equal-only run that borrowed another run's sweep
            where = f"from {sw['from']}"
        ax.set_title(f"seed scenario, {dname}, {where}", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    if eq is None:
        fig.tight_layout()
        C.save_figure(fig, path)
        return
    ax = axes[2]
    labels = [*eq.get("variants", VARIANTS), "diffrax Tsit5"]
    ax.barh(
        # In this part "RKMK4" is the array program forced (VARIANTS).
        [
            k.replace(" scalarized", "\nscalarized") if k != "RKMK4" else "RKMK4\narray"
            for k in labels
        ],
        [eq[k]["trajectories_per_s"] for k in labels],
        color=[f"C{i}" for i in range(len(labels))],
    )
    ax.set_xscale("log")
    ax.set_xlabel("trajectories / s")
    ax.tick_params(axis="y", labelsize=7)
    n_dev = eq.get("devices", 1)
    ax.set_title(
        f"{eq['batch']} x seed {eq['T']:g} s at attitude error 1e-8"
        f"{f', sharded over {n_dev} devices' if n_dev > 1 else ''}\n"
        f"best: {eq['best']['method']}, {eq['best']['speedup_over_tsit5']:.1f}x Tsit5",
        fontsize=9,
    )
    fig.tight_layout()
    C.save_figure(fig, path)


def main():
    def extra(p):
        p.add_argument(
            "--methods",
            nargs="+",
            help=f"subset of {list(LIE) + AMBIENT}, or variants {list(VARIANTS)[2:]} "
            f"and {list(SWEEP_VARIANTS)}",
        )
        p.add_argument("--batches", nargs="+", type=int, help="batch sizes of the sweep")
        p.add_argument(
            "--equal-only",
            action="store_true",
            help="rerun only the equal-accuracy part; keep the sweep of the existing JSON",
        )
        p.add_argument(
            "--dtypes",
            nargs="+",
            default=["float64", "float32"],
            choices=["float64", "float32"],
            help="dtypes of the sweep",
        )
        p.add_argument("--sweep-only", action="store_true", help="skip the equal-accuracy part")
        p.add_argument(
            "--variants",
            nargs="+",
            choices=list(VARIANTS),
            help="equal-accuracy variants to run (default all)",
        )
        p.add_argument(
            "--calibration",
            type=Path,
            help="take the step counts and Tsit5 tolerance from this earlier JSON "
            "(skips the search: dozens of compilations)",
        )
        p.add_argument(
            "--cpu-devices",
            type=int,
            default=1,
            help="run on this many CPU devices, every batch sharded across them "
            "(writes throughput-cpuN.json)",
        )

    args = C.parse_args(__doc__.splitlines()[0], extra)
    name = "throughput" if args.cpu_devices == 1 else f"throughput-cpu{args.cpu_devices}"
    json_path, png_path = C.output_paths(args, name)
    if args.equal_only:
        source = json_path if json_path.exists() else C.output_paths(args, "throughput")[0]
        old = json.loads(open(source).read())
        sw = {**old["sweep"], "measured": old.get("env", {}).get("date")}
        if source != json_path:
            sw["from"] = source.name
    else:
        sw = sweep(args, name)
    res = {"sweep": sw}
    if not args.sweep_only:
        res["equal_accuracy"] = equal_accuracy(args)
    res["env"] = C.environment()
    sw = res["sweep"]
    for dname in dict.fromkeys(r["dtype"] for r in sw["rows"]):
        rows = []
        for label in dict.fromkeys(r["method"] for r in sw["rows"]):
            rr = {r["batch"]: r for r in sw["rows"] if r["method"] == label and r["dtype"] == dname}
            row = {"method": label}
            row.update({f"B={b}": rr[b]["body_steps_per_s"] for b in sw["batches"] if b in rr})
            row["compile_s"] = rr[sw["batches"][0]]["compile_s"]
            row["mem_MB@max"] = rr[sw["batches"][-1]]["memory_mb"]
            rows.append(row)
        cols = ["method"] + [f"B={b}" for b in sw["batches"]] + ["compile_s", "mem_MB@max"]
        C.print_table(rows, cols, f"body-steps/s, {dname}, {sw['n_steps']} steps of {sw['dt']} s")
    if "equal_accuracy" not in res:
        C.write_json(json_path, res)
        plot(res, png_path)
        return
    eq = res["equal_accuracy"]
    title = (
        f"equal accuracy (1e-8): {eq['batch']} seed trajectories; steps {eq['n_steps']}, "
        f"errors {', '.join(f'{k} {v:.2g}' for k, v in eq['errors'].items())}; "
        f"Tsit5 tol = {eq['tsit5_tol']:.2g} (err {eq['tsit5_err']:.2g})"
    )
    C.print_table(
        [
            {"method": k, **eq[k], "x_tsit5": eq["speedup_over_tsit5"].get(k, 1.0)}
            for k in [*eq.get("variants", VARIANTS), "diffrax Tsit5"]
        ],
        [
            "method",
            "run_s",
            "trajectories_per_s",
            "body_steps_per_s",
            "mean_steps",
            "compile_s",
            "x_tsit5",
        ],
        title,
    )
    C.write_json(json_path, res)
    plot(res, png_path)


if __name__ == "__main__":
    main()
