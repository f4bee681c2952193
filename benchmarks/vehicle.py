"""The vehicle as it flies: what each optional model of the quadrotor costs per step.

`scenes.quadrotor` takes optional models of the vehicle: rotors with thrust limits
(`so3jax.Rotors`), their first-order lag, drag in a constant wind or a gust
(`so3jax.Gust`), integral action (`QuadrotorGains` with ``k_i``, ``k_I``) and sensor
noise (`so3jax.SensorNoise`). Without them the scene is the plain quadrotor, the same
program; with rotors, their lag and drag (``rotors, lag, drag``) the target is at most
1.5x the plain quadrotor's time per step, and the full vehicle (every model) is measured
beside it. Configurations, each a hover at the origin with the vehicle
and gains of Lee, Leok & McClamroch (CDC 2010, `scenes.quadrotor_recovery`), control
sampled and held every step (``control_period = dt = 2.5 ms``):

- ``plain``: `scenes.quadrotor_recovery` (the baseline of every ratio);
- ``plain, models off``: `scenes.quadrotor` with every model given and off (``rotors``,
  ``drag``, ``wind`` ``None``, ``k_i = k_I = 0``, a `SensorNoise` of zero intensity):
  its compiled program must be that of ``plain`` (``same_program_as_plain``), and its
  ratio measures the noise of the machine;
- ``rotors``: `Rotors` (arm 0.315 m, torque coefficient 0.02 m, thrust per rotor in
  ``[0, 2 m g / 4]``: thrust-to-weight 2), plain clipping;
- ``rotors, lag``: the same with a time constant of 30 ms (the thrusts are state);
- ``drag, wind``: drag of 2 N s/m per body axis in a constant wind of 4 m/s;
- ``drag, gust``: the same drag in a `Gust` (mean 4 m/s, intensity 1.5 m/s, correlation
  time 0.5 s), one gust per run;
- ``integral``: integral action, ``k_i = 10`` N/m, ``k_I = 0.5`` N m/rad;
- ``noise``: `SensorNoise` (attitude 0.01 rad, rate 0.05 rad/s, position 0.02 m,
  velocity 0.05 m/s), one key per run;
- ``full vehicle``: lagged rotors, drag in the gust, integral action and noise;
- ``rotors, lag, drag``: lagged rotors and drag in the constant wind, the vehicle the
  target is for (`TARGET_CONFIG`).

Each is ``jax.jit(jax.vmap(run))`` over 4096 random initial attitudes, RKMK4, 400 steps
(1 s), the final state saved, in float64 and float32 (the scene built in that dtype;
JAX's 64-bit mode on, as in every benchmark). Each configuration compiles once (timed
apart, JAX's caches cleared before each); after a warm-up call the configurations of
both dtypes are timed in alternated rounds, one call each per round, the first of a
round rotating: at least ``--repeats`` rounds (default 5), more (up to 30) until each
has run for 1 s. Each row keeps the fastest call, its body-steps/s (runs x steps /
time), its ratio to ``plain`` in the same dtype (the fastest over the fastest, and per
round), the compile time, a hash of the compiled program, the engine's layout for the
batch and why (`so3jax.explain`) and, as a check that the runs fly, the fraction of
finite runs and the median final distance from the hover point.

Writes ``results/vehicle[-quick].json`` and ``.png``: the ratio per configuration in
float64 and float32, with the 1.5x target.

    python benchmarks/vehicle.py            # 4096 runs: several minutes
    python benchmarks/vehicle.py --quick    # smoke run: 8 runs, 20 steps, plain and full, float32
"""

from __future__ import annotations

import hashlib
import math
import time

import _common as C
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import so3jax as s

DT = 0.0025
TARGET = 1.5
BASE = "plain"
ARM, TORQUE_COEFFICIENT, THRUST_TO_WEIGHT = 0.315, 0.02, 2.0
TIME_CONSTANT, DRAG, WIND = 0.03, 2.0, (4.0, 0.0, 0.0)
GUST = dict(mean=WIND, intensity=1.5, correlation_time=0.5)
INTEGRAL = dict(k_i=10.0, k_I=0.5)
NOISE = dict(attitude=0.01, rate=0.05, position=0.02, velocity=0.05)

#: Configuration -> the models it adds to the plain quadrotor.
CONFIGS = {
    "plain": {},
    "plain, models off": {"off": True},
    "rotors": {"rotors": True},
    "rotors, lag": {"rotors": True, "lag": True},
    "drag, wind": {"drag": True, "wind": "constant"},
    "drag, gust": {"drag": True, "wind": "gust"},
    "integral": {"integral": True},
    "noise": {"noise": True},
    "full vehicle": {"rotors": True, "lag": True, "drag": True, "wind": "gust",
                     "integral": True, "noise": True},
    "rotors, lag, drag": {"rotors": True, "lag": True, "drag": True, "wind": "constant"},
}  # fmt: skip
#: The configuration the target is for: the models the issue's benchmark names (lagged
#: rotors and drag, here in a constant wind).
TARGET_CONFIG = "rotors, lag, drag"
QUICK_CONFIGS, QUICK_DTYPES = ["plain", "full vehicle"], ["float32"]


def sizes(quick: bool) -> tuple[int, int]:
    """``(runs, steps)``."""
    return (8, 20) if quick else (4096, 400)


def scene(config: str, dtype, duration: float):
    """The hover scene of ``config`` in ``dtype`` (a gust and a noise key of its own: each
    run gets its own through `batch`)."""
    plain = s.scenes.quadrotor_recovery(control_period=DT, dtype=dtype)
    models = CONFIGS[config]
    if not models:
        return plain
    vehicle = plain.vehicle
    mass, g = float(vehicle.mass), float(vehicle.g)
    k = plain.gains
    gains = s.QuadrotorGains(
        k.k_x, k.k_v, k.k_R, k.k_Omega, **(INTEGRAL if models.get("integral") else {})
    )
    rotors = None
    if models.get("rotors"):
        rotors = s.Rotors(
            ARM,
            TORQUE_COEFFICIENT,
            thrust_min=0.0,
            thrust_max=THRUST_TO_WEIGHT * mass * g / 4,
            time_constant=TIME_CONSTANT if models.get("lag") else None,
        )
    wind = None
    if models.get("wind") == "constant":
        wind = np.asarray(WIND, dtype)
    elif models.get("wind") == "gust":
        wind = s.Gust(**GUST, duration=duration, key=jax.random.key(1), dtype=dtype)
    noise = None
    if models.get("noise"):
        noise = s.SensorNoise(**NOISE, key=jax.random.key(2))
    elif models.get("off"):
        noise = s.SensorNoise(key=jax.random.key(2))  # zero intensity: dropped
    return s.scenes.quadrotor(
        vehicle.mass,
        vehicle.body,
        gains,
        plain.reference,
        R0=np.eye(3, dtype=dtype),
        control_period=DT,
        rotors=rotors,
        drag=DRAG if models.get("drag") else None,
        wind=wind,
        noise=noise,
    )


def inputs(B: int, n_steps: int, dtype) -> tuple:
    """``(R0s, gust paths, noise keys)``: a random attitude, a gust and a key per run."""
    R0s = s.random_rotation(jax.random.key(0), (B,), dtype=dtype)
    keys = jax.random.split(jax.random.key(3), B)

    def gust(key):
        return s.Gust(**GUST, duration=n_steps * DT, key=key, dtype=dtype).path

    paths = jax.vmap(gust)(jax.random.split(jax.random.key(4), B))
    return R0s, paths, keys


def batch(sc, n_steps: int):
    """``f(R0s, paths, keys) -> (final position error, finite)``, vmapped over the runs."""
    method = s.RKMK4()

    def one(R0, path, key):
        run = sc
        if isinstance(run.wind, s.Gust):
            run = eqx.tree_at(lambda c: c.wind.path, run, path)
        if getattr(run, "noise", None) is not None:
            run = eqx.tree_at(lambda c: c.noise.key, run, key)
        tr = s.simulate(run, method, DT, n_steps, n_steps, R0=R0)
        x = tr.y.x[..., 3:6]  # position (the hover point is the origin)
        return jnp.linalg.norm(x), jnp.all(jnp.isfinite(tr.y.x))

    return jax.vmap(one)


def compile_all(jobs, B: int, n_steps: int, warm_up: bool) -> dict:
    """Each ``(dtype, config)`` compiled, with its inputs, hash, layout and outcome.

    JAX's caches are cleared before each compile: a configuration whose inner functions
    trace as another's did (``plain, models off``) would otherwise reuse their traces.
    ``warm_up``: first compile the plain scene for one step (another program), so that
    the first compile timed does not also pay what a process pays once.
    """
    compiled, args = {}, {}
    if warm_up and jobs:
        dtype = jnp.dtype(jobs[0][0])
        C.compile_fn(batch(scene(BASE, dtype, DT), 1), *inputs(B, 1, dtype))
    for dname, config in C.progress(jobs, "compile"):
        dtype = jnp.dtype(dname)
        if dname not in args:
            args[dname] = inputs(B, n_steps, dtype)
        fn = batch(scene(config, dtype, n_steps * DT), n_steps)
        layouts = s.explain(fn, *args[dname]).of("layout")
        jax.clear_caches()
        exe, compile_s, _ = C.compile_fn(fn, *args[dname])
        err, ok = jax.block_until_ready(exe(*args[dname]))  # the warm-up call
        err, ok = np.asarray(err, float), np.asarray(ok)
        compiled[(dname, config)] = {
            "exe": exe,
            "args": args[dname],
            "compile_s": compile_s,
            "program_hash": hashlib.sha1(exe.as_text().encode()).hexdigest()[:12],
            "layout": ", ".join(sorted({e["layout"] for e in layouts})) or None,
            "layout_why": "; ".join(sorted({e["why"] for e in layouts if e.get("why")})) or None,
            "finite_fraction": float(ok.mean()),
            "median_position_error": float(np.median(err[ok])) if ok.any() else None,
        }
    return compiled


def time_rounds(compiled: dict, repeats: int, min_s: float, max_rounds: int = 30) -> dict:
    """Call times per job over alternated rounds (at least ``repeats``, up to
    ``max_rounds`` until every job has run ``min_s``)."""
    names = list(compiled)
    times = {k: [] for k in names}
    r = 0
    while r < repeats or (min(sum(t) for t in times.values()) < min_s and r < max_rounds):
        for k in names[r % len(names) :] + names[: r % len(names)]:
            c = compiled[k]
            t = time.perf_counter()
            jax.block_until_ready(c["exe"](*c["args"]))
            times[k].append(time.perf_counter() - t)
        r += 1
    return times


def figure(data: dict):
    """The ratio to ``plain`` per configuration, float64 and float32, with the target."""
    configs = [c for c in data["configs"] if c != BASE]
    by = {(r["dtype"], r["config"]): r for r in data["rows"]}
    fig, ax = C.plt.subplots(
        figsize=(max(6.5, 1.0 + 0.9 * len(configs)), 4.2), layout="constrained"
    )
    width = 0.8 / len(data["dtypes"])
    for i, dname in enumerate(data["dtypes"]):
        rows = [by.get((dname, c)) for c in configs]
        vals = [math.nan if r is None else r["ratio"] for r in rows]
        xs = np.arange(len(configs)) + (i - (len(data["dtypes"]) - 1) / 2) * width
        ax.bar(xs, vals, width, label=dname, color=f"C{i}")
        for xi, r in zip(xs, rows, strict=True):
            if r is not None:
                ax.vlines(xi, *r["ratio_range"], color="k", lw=1.2)
                top = max(r["ratio"], r["ratio_range"][1]) * 1.05
                # (a label is left out of the layout: one far outside the axes collapsed it)
                ax.text(xi, top, f"{r['ratio']:.3g}", ha="center", fontsize=6, in_layout=False)
    ax.axhline(1.0, color="k", lw=0.8)
    ax.axhline(TARGET, color="C3", ls="--", lw=1.0, label=f"target {TARGET:g}x")
    ax.set_yscale("log")
    lows = [v for r in data["rows"] for v in (r["ratio"], r["ratio_range"][0])]
    lows = [v for v in lows if math.isfinite(v) and v > 0]
    ax.set_ylim(bottom=min([0.8, *(0.9 * v for v in lows)]))  # every bar starts in view
    ax.set_xticks(range(len(configs)), configs, rotation=30, ha="right")
    ax.set_ylabel("time per step / plain quadrotor's\n(lines: middle half of the rounds)")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=8)
    e = data["env"]
    machine = f"CPU, {e['cpu_count']} cores" if e["backend"] == "cpu" else e["device_kind"]
    ax.set_title(
        f"what each vehicle model costs:\n{data['batch']} runs, {data['n_steps']} steps, "
        f"RKMK4 ({machine})",
        fontsize=10,
    )
    return fig


def middle_half(values) -> list[float]:
    """The first and third quartiles."""
    return [float(q) for q in np.quantile(np.asarray(values, float), [0.25, 0.75])]


def main():
    def extra(p):
        p.set_defaults(repeats=5)
        p.add_argument("--configs", nargs="+", choices=list(CONFIGS), help="default: all")
        p.add_argument("--dtypes", nargs="+", choices=["float64", "float32"],
                       help="default: both (--quick: float32)")  # fmt: skip

    args = C.parse_args(__doc__.splitlines()[0], extra)
    B, n_steps = sizes(args.quick)
    configs = args.configs or (QUICK_CONFIGS if args.quick else list(CONFIGS))
    args.dtypes = args.dtypes or (QUICK_DTYPES if args.quick else ["float64", "float32"])
    if BASE not in configs:
        configs = [BASE, *configs]  # the baseline of every ratio
    jobs = [(d, c) for d in args.dtypes for c in configs]
    compiled = compile_all(jobs, B, n_steps, warm_up=not args.quick)
    times = time_rounds(compiled, args.repeats, 0.0 if args.quick else 1.0)
    rows = []
    for (dname, config), c in compiled.items():
        ts, base = times[(dname, config)], times[(dname, BASE)]
        per_round = [t / u for t, u in zip(ts, base, strict=True)]
        rows.append(
            {
                "dtype": dname,
                "config": config,
                "models": CONFIGS[config],
                "run_s": min(ts),
                "rounds": ts,
                "body_steps_per_s": B * n_steps / min(ts),
                "ratio": min(ts) / min(base),
                "ratio_rounds": per_round,
                "ratio_range": middle_half(per_round),
                "compile_s": c["compile_s"],
                "compile_ratio": c["compile_s"] / compiled[(dname, BASE)]["compile_s"],
                "program_hash": c["program_hash"],
                "same_program_as_plain": c["program_hash"]
                == compiled[(dname, BASE)]["program_hash"],
                "layout": c["layout"],
                "layout_why": c["layout_why"],
                "finite_fraction": c["finite_fraction"],
                "median_position_error": c["median_position_error"],
            }
        )
    data = {
        "benchmark": "vehicle",
        "quick": args.quick,
        "env": C.environment(),
        "method": "RKMK4",
        "batch": B,
        "n_steps": n_steps,
        "dt": DT,
        "control_period": DT,
        "target": TARGET,
        "target_config": TARGET_CONFIG,
        "dtypes": args.dtypes,
        "configs": {c: CONFIGS[c] for c in configs},
        "settings": {
            "arm": ARM,
            "torque_coefficient": TORQUE_COEFFICIENT,
            "thrust_to_weight": THRUST_TO_WEIGHT,
            "time_constant": TIME_CONSTANT,
            "drag": DRAG,
            "wind": WIND,
            "gust": GUST,
            "integral": INTEGRAL,
            "noise": NOISE,
        },
        "repeats": args.repeats,
        "rows": rows,
    }
    C.print_table(
        [
            {
                "dtype": r["dtype"],
                "config": r["config"],
                "ms": r["run_s"] * 1e3,
                "body-steps/s": r["body_steps_per_s"],
                "x plain": r["ratio"],
                "compile s": r["compile_s"],
                "same program": r["same_program_as_plain"],
                "layout": r["layout"],
                "finite": r["finite_fraction"],
                "|x| final": r["median_position_error"],
            }
            for r in rows
        ],
        ["dtype", "config", "ms", "body-steps/s", "x plain", "compile s", "same program",
         "layout", "finite", "|x| final"],
        title=f"each vehicle model's time per step over the plain quadrotor's (target {TARGET}x)",
    )  # fmt: skip
    json_path, png_path = C.output_paths(args, "vehicle")
    C.write_json(json_path, data)
    C.save_figure(figure(data), png_path)


if __name__ == "__main__":
    main()
