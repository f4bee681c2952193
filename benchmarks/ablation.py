"""What each optimisation pass of the execution engine buys: every pass off in turn.

Configurations (`so3jax._engine.policy`): "all passes" (the default), each of
`so3jax._engine.policy.PASSES` off alone ("no hoist", ...), "none" (every pass off: the
reference programs, with the engine's derivative strategies) and, where the API takes a
program, "autodiff" (every pass off and ``program="autodiff"``: the checkpointed
``lax.scan`` differentiated by JAX alone). Workloads, float64, RKMK4:

- ``run``: one seed run, ``simulate(scenes.seed(), RKMK4(), 0.01, 1000)``, every state
  saved;
- ``batch``: ``vmap`` of `so3jax.simulate` over 4096 random initial attitudes (``R0=``),
  100 steps, the final state saved;
- ``grad``: `jax.grad` of `so3jax.expected_cost` over 256 starts with respect to
  ``(k_R, k_Omega)``, 200 steps;
- ``large grad``: the same over 1024 starts, where a batch of Jacobian programs runs in
  cache-sized tiles (the ``tiles`` pass: sixteen tiles here, four over 256 starts);
- ``small grad``: the same over 8 starts, a batch below the scalarized layout's
  threshold: the array program, vmapped (where the ``settle`` pass acts);
- ``run grad``: `jax.grad` of one run's cost, the sum of ``|Omega|^2`` over the 1000 saved
  states of ``run``, with respect to ``(k_R, k_Omega)``, no `vmap`: the derivative program
  is the array layout, whose loop the engine hoists only with its small reductions
  written out (the ``unroll`` pass);
- ``LGVI grad``: the same gradient with the variational integrator `so3jax.LGVI`, whose
  step solves an implicit equation by Newton iterations;
- ``quadrotor``: the forward pass of DiffTune's quadrotor loss (``difftune.py``: the sum
  of ``|e_x|^2`` over the samples of Lee's controller on the 10 s circle), 800 steps of
  2.5 ms;
- ``quadrotor grad``: its `jax.value_and_grad` with respect to the 12 gains.

`so3jax.simulate` takes no program: "autodiff" is measured on ``grad`` and ``small grad``
only. Past the
policy's ``forward_jacobian_max`` differentiated scalars (the quadrotor's 12 gains) the
engine's reverse mode is its discrete adjoint from checkpointed segments.

Each configuration compiles each workload `COMPILE_ROUNDS` times, in alternated rounds (timed
apart, JAX's caches cleared before each, `_common.engine_settings`), and keeps the fastest
compilation and, apart, the fastest tracing and lowering (the engine's share of it);
after a warm-up call the configurations of a
workload are timed in alternated rounds, one call each per round, the first configuration
of a round rotating: at least ``--repeats`` rounds (default 3), more (up to 50) until each
configuration has run for 0.5 s (a call of a few milliseconds on a shared machine needs
more than three for its minimum). Each row keeps the fastest call, the range over rounds,
the compile time, a hash of the compiled program (a pass that leaves a workload's program
unchanged is seen as such, whatever the timing noise) and the largest difference of the
outputs from those of "all passes", relative to their largest magnitude.

Writes ``results/ablation[-quick].json`` and ``.png``: per workload, the time of each
configuration over that of "all passes" (log scale; pale where the program is the same).

    python benchmarks/ablation.py            # the sizes above: several minutes
    python benchmarks/ablation.py --quick    # smoke run: a 20-step run, "all passes" and "none"
    python benchmarks/ablation.py --workloads "large grad" --merge  # one workload again
    python benchmarks/ablation.py --compile-rounds 1  # on a device lease (`gpu.sh ablation`)

After each workload, ``ablation[-<backend>][-quick].partial.json`` holds the workloads
finished, in the final file's schema: a run cut off keeps them.
``--merge`` measures the workloads named and replaces their rows in the existing results
(every ratio is within one workload; ``merged`` gives the environment of each workload
measured apart).
"""

from __future__ import annotations

import hashlib
import json
import math
import time

import _common as C
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import so3jax as so3
from so3jax._engine import policy
from so3jax._tune import with_gains

DT_QUAD = 0.0025

#: Configuration -> (passes, program). "autodiff" runs only where a workload takes a program.
CONFIGS = {
    "all passes": (policy.PASSES, "auto"),
    **{f"no {p}": (policy.PASSES - {p}, "auto") for p in sorted(policy.PASSES)},
    "none": (frozenset(), "auto"),
    "autodiff": (frozenset(), "autodiff"),
}
BASE = "all passes"


#: Each workload's size (steps, or (runs, steps)), ``(quick, full)``.
SIZES = {
    "run": (20, 1000),
    "batch": ((32, 10), (4096, 100)),
    "grad": ((16, 10), (256, 200)),
    "large": ((32, 10), (1024, 200)),
    "small": (4, 8),
    "LGVI": (20, 1000),
    "quadrotor": (20, 800),
}


def sizes(quick: bool) -> dict:
    return {name: quick_full[0 if quick else 1] for name, quick_full in SIZES.items()}


def workloads(quick: bool) -> dict:
    """Name -> (label, ``make(program) -> (fn, arg)``, whether it takes a program)."""
    n = sizes(quick)
    seed, method = so3.scenes.seed(), so3.RKMK4()

    def run(program):
        def fn(sc):
            tr = so3.simulate(sc, method, 0.01, n["run"])
            return tr.R, tr.Omega

        return fn, seed

    B, steps = n["batch"]
    R0s = so3.random_rotation(jax.random.key(0), (B,))

    def batch(program):
        def one(R):
            tr = so3.simulate(seed, method, 0.01, steps, steps, R0=R)
            return tr.R[-1], tr.Omega[-1]

        return jax.vmap(one), R0s

    Bg, steps_g = n["grad"]
    R0, W0 = so3.initial_states(jax.random.key(1), Bg)

    def mean_grad(R0, W0):
        def make(program):
            def cost(k):
                return so3.expected_cost(
                    seed, k[0], k[1], R0, W0, method, 1e-2, steps_g, program=program
                )

            return jax.grad(cost), jnp.array([8.81, 2.54])

        return make

    Bl, Bs = n["large"][0], n["small"]
    grad, small_grad = mean_grad(R0, W0), mean_grad(R0[:Bs], W0[:Bs])
    large_grad = mean_grad(*so3.initial_states(jax.random.key(1), Bl))

    def run_grad_of(m, steps):
        def make(program):
            def cost(k):
                tr = so3.simulate(with_gains(seed, k[0], k[1]), m, 0.01, steps)
                return jnp.sum(tr.Omega**2)

            return jax.grad(cost), jnp.array([8.81, 2.54])

        return make

    quad = so3.scenes.quadrotor_circle(control_period=DT_QUAD)
    steps_q = n["quadrotor"]

    def loss(g):
        sc = eqx.tree_at(lambda s: s.gains, quad, g)
        return jnp.sum(so3.simulate(sc, method, DT_QUAD, steps_q).extras["e_x"] ** 2)

    return {
        "run": (f"one run, {n['run']} steps", run, False),
        "batch": (f"`vmap` of {B} runs, {steps} steps", batch, False),
        "grad": (f"`grad` over {Bg} runs, {steps_g} steps", grad, True),
        "large grad": (f"`grad` over {Bl} runs, {steps_g} steps", large_grad, False),
        "small grad": (f"`grad` over {Bs} runs, {steps_g} steps", small_grad, True),
        "run grad": (f"`grad`, one run, {n['run']} steps", run_grad_of(method, n["run"]), False),
        "LGVI grad": (
            f"`grad`, one run, LGVI, {n['LGVI']} steps",
            run_grad_of(so3.LGVI(), n["LGVI"]),
            False,
        ),
        "quadrotor": (f"quadrotor loss, {steps_q} steps", lambda p: (loss, quad.gains), False),
        "quadrotor grad": (
            "its value and gradient (12 gains)",
            lambda p: (jax.value_and_grad(loss), quad.gains),
            False,
        ),
    }


def rel_diff(out, ref) -> float:
    """Largest ``|out - ref|`` over the largest ``|ref|``, over every leaf."""
    a = [np.asarray(v, float) for v in jax.tree.leaves(out)]
    b = [np.asarray(v, float) for v in jax.tree.leaves(ref)]
    scale = max(float(np.max(np.abs(v))) for v in b) or 1.0
    return max(float(np.max(np.abs(u - v))) for u, v in zip(a, b, strict=True)) / scale


#: Compilations of each workload per configuration, in alternated rounds (JAX's caches
#: cleared before each): the fastest is reported, with the range. A pass can buy tracing
#: time alone (``settle``), and one compilation varies by more than the 10 % asked of it.
COMPILE_ROUNDS = 3


def measure(
    make, takes_program: bool, configs: list[str], repeats: int, min_s: float, compiles: int
):
    """One workload in every configuration: compiled apart ``compiles`` times in alternated
    rounds, timed in alternated rounds (at least ``repeats``, and up to 50 until every
    configuration has run ``min_s``)."""
    compiled, compile_times = {}, {}
    for k in range(compiles):
        for name in configs:
            passes, program = CONFIGS[name]
            if program != "auto" and not takes_program:
                continue
            with C.engine_settings(passes=passes):
                fn, arg = make(program)
                t = time.perf_counter()
                lowered = jax.jit(fn).trace(arg).lower()  # the engine's share: tracing
                traced = time.perf_counter()
                exe = lowered.compile()
                done = time.perf_counter()
            compile_times.setdefault(name, []).append((done - t, traced - t))
            if k == 0:
                out = jax.block_until_ready(exe(arg))  # the warm-up call
                digest = hashlib.sha1(exe.as_text().encode()).hexdigest()[:12]
                compiled[name] = (exe, arg, digest, out)
    names = list(compiled)
    times = {name: [] for name in names}
    r = 0
    while r < repeats or (min(sum(t) for t in times.values()) < min_s and r < 50):
        for name in names[r % len(names) :] + names[: r % len(names)]:
            exe, arg = compiled[name][:2]
            t = time.perf_counter()
            jax.block_until_ready(exe(arg))
            times[name].append(time.perf_counter() - t)
        r += 1
    base = compiled.get(BASE)
    rows = []
    for name in names:
        _, _, digest, out = compiled[name]
        ts = times[name]
        cs, trs = (list(x) for x in zip(*compile_times[name], strict=True))
        rows.append(
            {
                "config": name,
                "passes_off": sorted(policy.PASSES - CONFIGS[name][0]),
                "program": CONFIGS[name][1],
                "run_s": min(ts),
                "run_s_range": [min(ts), max(ts)],
                "rounds": ts,
                "compile_s": min(cs),
                "compile_s_rounds": cs,
                "trace_s": min(trs),
                "trace_s_rounds": trs,
                "program_hash": digest,
                "same_program_as_base": None if base is None else digest == base[2],
                "max_rel_diff": None if base is None else rel_diff(out, base[3]),
            }
        )
    return rows


def figure(data: dict):
    """Per workload, each configuration's time over that of "all passes" (log scale)."""
    wl = list(data["workloads"])
    configs = [c for c in data["configs"] if c != BASE]
    by = {(r["workload"], r["config"]): r for r in data["rows"]}
    ncols = min(3, len(wl))
    nrows = math.ceil(len(wl) / ncols)
    fig, axes = C.plt.subplots(
        nrows, ncols, figsize=(3.4 * ncols, 3.6 * nrows), sharey=True, squeeze=False
    )
    for ax in axes.flat[len(wl) :]:
        ax.set_visible(False)
    for ax, w in zip(axes.flat, wl, strict=False):
        base = by.get((w, BASE))
        vals = [
            by[(w, c)]["run_s"] / base["run_s"] if base and (w, c) in by else math.nan
            for c in configs
        ]
        colors = ["0.6" if c in ("none", "autodiff") else "C0" for c in configs]
        bars = ax.bar(range(len(configs)), vals, color=colors)
        for bar, c in zip(bars, configs, strict=True):  # the same program: the bar is noise
            if (w, c) in by and by[(w, c)]["same_program_as_base"]:
                bar.set_alpha(0.3)
        ax.axhline(1.0, color="k", lw=0.8)
        ax.axhline(1.1, color="k", ls=":", lw=0.8)
        ax.set_xticks(range(len(configs)), configs, rotation=60, ha="right", fontsize=8)
        ax.set_yscale("log")
        ax.set_title(data["workloads"][w]["label"].replace("`", ""), fontsize=9)
        ax.grid(alpha=0.3, axis="y")
    for ax in axes[:, 0]:
        ax.set_ylabel("time / time with all passes\n(dotted: 1.1)")
    axes[0, 0].text(0.02, 0.97, "pale: same program", transform=axes[0, 0].transAxes, va="top")
    e = data["env"]
    machine = f"CPU, {e['cpu_count']} cores" if e["backend"] == "cpu" else e["device_kind"]
    fig.suptitle(f"what each engine pass buys: slowdown with it off ({machine}, float64)")
    fig.tight_layout()
    return fig


def merged(path, new: dict) -> dict:
    """The results at ``path`` with ``new``'s workloads measured again (their rows
    replaced), in the existing workloads' order, new ones last."""
    old = json.loads(path.read_text())
    if old["configs"] != new["configs"] or old["quick"] != new["quick"]:
        raise ValueError(f"--merge: {path} has other configurations; run every workload")
    ours = set(new["workloads"])
    out = dict(old)
    out["workloads"] = {**old["workloads"], **new["workloads"]}
    out["rows"] = [r for r in old["rows"] if r["workload"] not in ours] + new["rows"]
    out["merged"] = {**old.get("merged", {}), **dict.fromkeys(ours, new["env"])}
    order = list(out["workloads"])
    out["rows"].sort(key=lambda r: order.index(r["workload"]))
    return out


def results(args, wl: dict, names: list[str], configs: list[str], rows: list[dict]) -> dict:
    """The JSON of the workloads ``names`` of ``wl`` (`workloads`) measured so far (their
    ``rows``)."""
    n = sizes(args.quick)
    base = {r["workload"]: r for r in rows if r["config"] == BASE}
    for r in rows:
        r["ratio"] = r["run_s"] / base[r["workload"]]["run_s"]
        r["compile_ratio"] = r["compile_s"] / base[r["workload"]]["compile_s"]
    return {
        "benchmark": "ablation",
        "quick": args.quick,
        "env": C.environment(),
        "dtype": "float64",
        "method": "RKMK4 (LGVI where a workload names it)",
        "repeats": args.repeats,
        "compile_rounds": args.compile_rounds,
        "passes": sorted(policy.PASSES),
        "configs": {
            c: {"passes_off": sorted(policy.PASSES - CONFIGS[c][0]), "program": CONFIGS[c][1]}
            for c in configs
        },
        "workloads": {
            w: {"label": wl[w][0], "takes_program": wl[w][2], "size": n[w.split()[0]]}
            for w in names
        },
        "rows": rows,
    }


def main():
    def extra(p):
        p.set_defaults(repeats=3)
        p.add_argument("--configs", nargs="+", choices=list(CONFIGS), help="default: all")
        p.add_argument("--workloads", nargs="+", help="default: all (--quick: run)")
        p.add_argument(
            "--compile-rounds",
            type=int,
            default=None,
            help=f"compilations of each workload per configuration (default {COMPILE_ROUNDS}"
            ", --quick: 1); fewer for a device lease with a time limit",
        )
        p.add_argument(
            "--merge",
            action="store_true",
            help="replace these workloads' rows in the existing results, keep the others",
        )

    args = C.parse_args(__doc__.splitlines()[0], extra)
    if args.compile_rounds is None:
        args.compile_rounds = 1 if args.quick else COMPILE_ROUNDS
    wl = workloads(args.quick)
    names = args.workloads or (["run"] if args.quick else list(wl))
    unknown = set(names) - set(wl)
    if unknown:
        raise ValueError(f"--workloads: unknown {sorted(unknown)}; known: {list(wl)}")
    configs = args.configs or ([BASE, "none"] if args.quick else list(CONFIGS))
    if BASE not in configs:
        configs = [BASE, *configs]  # the baseline of every ratio
    json_path, png_path = C.output_paths(args, "ablation")
    rows = []
    for i, w in enumerate(C.progress(names, "ablation")):
        label, make, takes_program = wl[w]
        min_s = 0.0 if args.quick else 0.5
        for r in measure(make, takes_program, configs, args.repeats, min_s, args.compile_rounds):
            rows.append({"workload": w, **r})
        # What finished, in the final schema: a run cut off keeps its complete workloads.
        partial = results(args, wl, names[: i + 1], configs, rows)
        C.write_json(json_path.with_suffix(".partial.json"), partial, quiet=True)
    data = results(args, wl, names, configs, rows)
    C.print_table(
        [
            {
                "workload": r["workload"],
                "config": r["config"],
                "ms": r["run_s"] * 1e3,
                "x all passes": r["ratio"],
                "compile s": r["compile_s"],
                "same program": r["same_program_as_base"],
                "rel diff": r["max_rel_diff"],
            }
            for r in rows
        ],
        ["workload", "config", "ms", "x all passes", "compile s", "same program", "rel diff"],
        title="time with each pass off, over the time with all passes",
    )
    if args.merge:
        data = merged(json_path, data)
    C.write_json(json_path, data)
    C.save_figure(figure(data), png_path)


if __name__ == "__main__":
    main()
