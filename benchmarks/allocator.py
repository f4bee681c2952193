"""The allocator's share of a call: glibc's defaults against buffers kept between calls.

XLA's CPU runtime allocates a program's temporaries as one buffer each call, and its
outputs as buffers of their own. glibc's ``malloc`` serves an allocation larger than its
mmap threshold (raised as the process frees such blocks, to at most 32 MiB) with fresh
pages from the kernel and unmaps them at ``free``, so every call faults every page in
again, and the kernel zeroes each one. A thread other than the main one allocates from
an arena whose heaps hold at most 64 MiB, so a larger buffer is mapped afresh whatever
the threshold; XLA runs its programs on such threads.

This script runs the same programs in child processes under two environments, alternated
over ``--rounds``:

- ``glibc defaults``: no ``MALLOC_*`` variable, ``GLIBC_TUNABLES`` or ``LD_PRELOAD``;
- ``buffers kept``: ``MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=4294967296
  MALLOC_ARENA_MAX=1``: one arena, freed memory kept for the next call. The first two
  alone leave a buffer over 64 MiB mapped afresh (above).

For each program it reports the fastest call over all rounds, XLA's temp memory, the
ratio of the two environments' times, and for each derivative its ratio to the forward
pass of the same cost under the same environment (issue 11's gradient target is at most
3x). The library sets no allocator option: like JAX's configuration they are the
process's, read by glibc when the process starts.

Programs (float64, RKMK4, dt 1e-2, the seed scenario from random starts, gains
(8.81, 2.54)):

- a user's own cost on saved runs (``tune.py --cost trajectory``: the mean
  ``tracking_cost(simulate(...))``, every state saved) at B = 256 runs of 1000 steps and
  B = 16 runs of 4000: the forward pass, ``grad`` and ``jacfwd`` in ``(k_R, k_Omega)``;
- ``expected_cost`` (the cost summed as the runs step, nothing saved) at B = 256, 1000
  steps: the forward pass and ``grad``;
- ``vmap(simulate)`` over 4096 starts, 1000 steps, every 10th state saved (its
  trajectories are the call's outputs: 101 points of 33 numbers a run).

Writes ``results/allocator[-quick].json`` and ``.png``.

    python benchmarks/allocator.py             # every program, 2 rounds
    python benchmarks/allocator.py --quick     # smoke run: Lie-Euler, tiny sizes, 1 round
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import _common as C
import matplotlib.pyplot as plt

#: The two environments: the variables each child gets on top of this process's
#: environment, from which every allocator variable (`_common.allocator`) is dropped.
SETTINGS = {
    "glibc defaults": {},
    "buffers kept": {
        "MALLOC_MMAP_THRESHOLD_": "4294967296",
        "MALLOC_TRIM_THRESHOLD_": "4294967296",
        "MALLOC_ARENA_MAX": "1",
    },
}


def programs(quick: bool) -> list[tuple[str, str, int, int]]:
    """(cost, derivative, runs, steps) of each program, forward passes first per cost."""
    if quick:
        return [("trajectory", d, 2, 50) for d in ("forward", "grad")]
    rows = []
    for B, n in ((256, 1000), (16, 4000)):
        rows += [("trajectory", d, B, n) for d in ("forward", "grad", "jacfwd")]
    rows += [("expected", d, 256, 1000) for d in ("forward", "grad")]
    rows.append(("simulate", "forward", 4096, 1000))
    return rows


def _child(quick: bool, repeats: int, min_seconds: float) -> list[dict]:
    """Measure every program in this process (run under one setting)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    from tune import measure, trajectory_cost

    import so3jax as so3
    from so3jax._tune import with_gains

    method = so3.LieEuler() if quick else so3.RKMK4()
    scene = so3.scenes.seed()
    k = jnp.array([8.81, 2.54])
    rows = []
    for cost, derivative, B, n in programs(quick):
        R0, W0 = so3.initial_states(jax.random.key(0), B)
        if cost == "trajectory":

            def f(k, R0=R0, W0=W0, n=n):
                return trajectory_cost(scene, k, R0, W0, method, n)

        elif cost == "expected":

            def f(k, R0=R0, W0=W0, n=n):
                return so3.expected_cost(scene, k[0], k[1], R0, W0, method, 1e-2, n)

        else:

            def f(k, R0=R0, n=n):
                sc = with_gains(scene, k[0], k[1])
                return jax.vmap(lambda R: so3.simulate(sc, method, 1e-2, n, 10, R0=R))(R0)

        fn = {"forward": f, "grad": jax.grad(f), "jacfwd": jax.jacfwd(f)}[derivative]
        r = measure(fn, k, repeats, min_seconds)
        r.update(cost=cost, derivative=derivative, batch=B, n_steps=n, seen=C.allocator())
        rows.append(r)
    return rows


def _run_child(setting: str, quick: bool, repeats: int, min_seconds: float) -> list[dict]:
    # What `C.allocator` reports (glibc's variables, a preloaded allocator) is dropped:
    # each child sees its setting's variables and no others.
    env = {k: v for k, v in os.environ.items() if k not in C.allocator()}
    env.update(SETTINGS[setting])
    args = [sys.executable, __file__, "--child", "--repeats", str(repeats)]
    args += ["--min-seconds", str(min_seconds)]
    out = subprocess.run(
        args + (["--quick"] if quick else []),
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if out.returncode != 0:
        raise RuntimeError(f"the child under {setting!r} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _key(r: dict) -> tuple:
    return (r["cost"], r["derivative"], r["batch"], r["n_steps"])


def combine(runs: dict[str, list[list[dict]]]) -> list[dict]:
    """One row per program and setting: the fastest call over the rounds, the ratio to the
    forward pass of the same cost and size under the same setting, and (for the kept
    buffers) the ratio to the defaults."""
    rows = []
    for setting, rounds in runs.items():
        for i in range(len(rounds[0])):
            best = min((r[i] for r in rounds), key=lambda r: r["seconds"])
            rows.append(dict(best, setting=setting, rounds=[r[i]["seconds"] for r in rounds]))
    by = {(r["setting"],) + _key(r): r for r in rows}
    for r in rows:
        fwd = by.get((r["setting"], r["cost"], "forward", r["batch"], r["n_steps"]))
        r["forward_ratio"] = r["seconds"] / fwd["seconds"] if fwd else None
        base = by[("glibc defaults",) + _key(r)]
        r["time_ratio"] = r["seconds"] / base["seconds"]
    return rows


def label(r: dict) -> str:
    return f"{r['cost']} {r['derivative']}\nB={r['batch']}, {r['n_steps']} steps"


def figure(rows: list[dict]):
    """Each program's fastest call under both settings, and the derivatives' ratios to
    the forward pass (the forward passes, the baselines, are left blank)."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    names = list(dict.fromkeys(label(r) for r in rows))
    width = 0.8 / len(SETTINGS)
    for i, setting in enumerate(SETTINGS):
        mine = {label(r): r for r in rows if r["setting"] == setting}
        xs = [j + width * i for j in range(len(names))]
        axes[0].bar(xs, [mine[n]["seconds"] * 1e3 for n in names], width=width, label=setting)
        ratios = [
            mine[n]["forward_ratio"] if mine[n]["derivative"] != "forward" else 0 for n in names
        ]
        axes[1].bar(xs, ratios, width=width, label=setting)
    for ax in axes:
        ax.set_xticks([j + 0.4 - width / 2 for j in range(len(names))], names, fontsize=6)
        ax.tick_params(axis="x", labelrotation=60)
        ax.legend(fontsize=8)
    axes[0].set_ylabel("fastest call [ms]")
    axes[0].set_yscale("log")
    axes[1].set_ylabel("time / forward pass of the same cost")
    axes[1].axhline(3, color="k", ls=":", lw=1)
    fig.suptitle(f"glibc's allocator and XLA's buffers, {C.environment()['device_kind']}")
    return fig


def main():
    def extra(p):
        p.add_argument("--rounds", type=int, default=None, help="default 2 (--quick: 1)")
        p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
        p.add_argument(
            "--min-seconds", type=float, default=None, help="least time per row (default 0.5 s)"
        )

    args = C.parse_args(__doc__, extra)
    if args.min_seconds is None:
        args.min_seconds = 0.05 if args.quick else 0.5
    if args.child:
        print(json.dumps(_child(args.quick, args.repeats, args.min_seconds)))
        return
    rounds = args.rounds or (1 if args.quick else 2)
    runs = {s: [] for s in SETTINGS}
    t0 = time.perf_counter()
    for i in range(rounds):
        for setting in SETTINGS:
            runs[setting].append(_run_child(setting, args.quick, args.repeats, args.min_seconds))
            print(f"round {i + 1}/{rounds}, {setting}: done at {time.perf_counter() - t0:.0f} s")
    rows = combine(runs)
    C.print_table(
        rows,
        [
            "setting",
            "cost",
            "derivative",
            "batch",
            "n_steps",
            "seconds",
            "forward_ratio",
            "time_ratio",
            "temp_bytes",
        ],
    )
    json_path, png_path = C.output_paths(args, "allocator")
    C.write_json(
        json_path,
        {
            "benchmark": "allocator",
            "quick": args.quick,
            "settings": SETTINGS,
            "env": C.environment(),
            "rows": rows,
        },
    )
    C.save_figure(figure(rows), png_path)


if __name__ == "__main__":
    main()
