"""First-call latency: what a user waits for before the first number, in a fresh process.

A notebook or a script starts a new Python process; its first call of each library
function pays for every XLA program that call compiles. An eagerly called function
that dispatches its operations one by one compiles each of them (about 20 to 50 ms
each on this CPU) the first time it meets them; a jitted one compiles one program.
For each entry point (scene constructors, attitude sampling, the public primitives on
a batch, the first `simulate`), this script starts a fresh process, imports so3jax
(timed apart), runs the entry once ("cold": compilations included) and again
("warm"), and counts XLA compilations of the cold call (`jax_log_compiles`).

``--baseline PATH`` runs every entry also against the so3jax package found in
``PATH`` (another checkout, e.g. ``git worktree add /tmp/base HEAD~1``), alternating
the two in fresh processes, so the JSON has both columns from one run.

``--persistent-cache`` adds a column with JAX's persistent compilation cache on
(``JAX_COMPILATION_CACHE_DIR``, a fresh temporary folder, every program stored): one
fresh process per entry fills it, then the timed processes read it, as a notebook
does after a kernel restart. (A program with a host callback is not stored; a ``dt``
given as a number adds none.)

Writes ``results/startup[-quick].json`` and ``.png``.

    python benchmarks/startup.py                            # every entry, 5 repeats
    python benchmarks/startup.py --baseline /tmp/base       # with the old code beside it
    python benchmarks/startup.py --quick                    # smoke run: one entry
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile

import _common as C
import numpy as np

#: name -> (setup, timed statement). Both run after ``import so3jax as s`` (x64 on);
#: the statement assigns ``out``, which is blocked on before the clock stops.
ENTRIES = {
    "scenes.seed()": ("", "out = s.scenes.seed()"),
    "scenes.free_body(...)": (
        "",
        "out = s.scenes.free_body([1.0, 2.0, 3.0], np.eye(3), [0.1, 2.0, 0.05])",
    ),
    "scenes.dzhanibekov()": ("", "out = s.scenes.dzhanibekov()"),
    "scenes.unwinding(True)": ("", "out = s.scenes.unwinding(hysteresis=True)"),
    "scenes.quadrotor_circle()": ("", "out = s.scenes.quadrotor_circle()"),
    "random_rotation(key, 4096)": (
        "key = jax.random.key(0)",
        "out = s.random_rotation(key, (4096,))",
    ),
    "primitives on 256 rotations": (
        "R = np.asarray(s.random_rotation(jax.random.key(0), (256,)))\nw = np.asarray(s.log(R))",
        "out = (s.exp(w), s.log(R), s.to_euler_zyx(R), s.from_euler_zyx(0.1, 0.2, 0.3),\n"
        "       s.attitude_error_function(R, R[::-1]), s.orthogonality_error(R),\n"
        "       s.geodesic_distance(R, R[::-1]), s.hat(w), s.vee(R), s.to_quat(R))",
    ),
    "first simulate(seed, RKMK4, 1000 steps)": (
        "scene = s.scenes.seed(); m = s.RKMK4()",
        "out = s.simulate(scene, m, dt=1e-2, n_steps=1000, save_every=10)",
    ),
    "vmap(simulate), 2048 seed starts": (
        "scene = s.scenes.seed(); m = s.RKMK4()\n"
        "R0s = s.random_rotation(jax.random.key(0), (2048,))",
        "out = jax.vmap(lambda R: s.simulate(scene, m, 1e-2, 1000, 1000, R0=R).R)(R0s)",
    ),
    "grad of expected_cost, 16 starts": (
        "scene = s.scenes.seed(); R0, W0 = s.initial_states(jax.random.key(0), 16)\n"
        "k = jax.numpy.array([8.81, 2.54])",
        "out = jax.grad(lambda k: s.expected_cost(scene, k[0], k[1], R0, W0, s.RKMK4(),"
        " 1e-2, 1000))(k)",
    ),
}

_CHILD = r"""
import json, logging, sys, time
t0 = time.perf_counter()
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import so3jax as s
t_import = time.perf_counter() - t0
compiles = [0]

class Count(logging.Handler):
    def emit(self, record):
        if record.getMessage().startswith("Finished XLA compilation"):
            compiles[0] += 1

log = logging.getLogger("jax")
log.addHandler(Count())
log.setLevel(logging.WARNING)
log.propagate = False
setup, stmt = json.loads(sys.argv[1])
env = {"s": s, "jax": jax, "np": np}
exec(setup, env)
jax.block_until_ready([v for v in env.values() if isinstance(v, jax.Array)])
jax.config.update("jax_log_compiles", True)
times = []
for _ in range(2):
    n0 = compiles[0]
    t = time.perf_counter()
    exec(stmt, env)
    jax.block_until_ready(env["out"])
    times.append(time.perf_counter() - t)
    if len(times) == 1:
        n_cold = compiles[0] - n0
print(json.dumps({"import_s": t_import, "cold_s": times[0], "warm_s": times[1],
                  "compiles": n_cold}))
"""


def _child(entry: str, path: str | None, cache: str | None = None) -> dict:
    env = dict(os.environ)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # cold means cold, whatever the caller's setting
    if path:  # the other checkout's package first on the path
        env["PYTHONPATH"] = os.pathsep.join([path] + env.get("PYTHONPATH", "").split(os.pathsep))
    if cache:  # JAX reads its flags from these variables: store every program
        env["JAX_COMPILATION_CACHE_DIR"] = cache
        env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
        env["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, json.dumps(ENTRIES[entry])],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        cwd=path or None,
    )
    if out.returncode:
        raise RuntimeError(f"{entry!r} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _label(path: str) -> str:
    """``baseline <commit>`` when ``path`` is a git checkout."""
    out = subprocess.run(
        ["git", "-C", path, "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    )
    return f"baseline {out.stdout.strip()}" if out.returncode == 0 else "baseline"


def main():
    def extra(p):
        p.add_argument("--baseline", default=None, help="a checkout whose so3jax is the baseline")
        p.add_argument(
            "--persistent-cache",
            action="store_true",
            help="add a column with JAX's persistent compilation cache on (filled first)",
        )
        p.add_argument(
            "--entries",
            nargs="+",
            default=None,
            metavar="SUBSTRING",
            help="only the entries whose name contains one of these (e.g. simulate grad)",
        )

    args = C.parse_args(__doc__.splitlines()[0], extra)
    entries = ["scenes.seed()"] if args.quick else list(ENTRIES)
    if args.entries:
        entries = [e for e in ENTRIES if any(k in e for k in args.entries)]
        if not entries:
            raise SystemExit(f"no entry matches {args.entries}; entries: {list(ENTRIES)}")
    repeats = 1 if args.quick else args.repeats
    codes = {"current": (None, None)}
    if args.baseline:
        codes[_label(args.baseline)] = (args.baseline, None)
    cache_dir = None
    if args.persistent_cache:
        cache_dir = tempfile.mkdtemp(prefix="so3jax-startup-cache-")
        codes["current, persistent cache"] = (None, cache_dir)
        for e in C.progress(entries, "filling the cache"):
            _child(e, None, cache_dir)
    runs = {(e, c): [] for e in entries for c in codes}
    try:
        for _ in C.progress(range(repeats), "repeats"):
            for e in entries:
                for c, (path, cache) in codes.items():  # alternated: same machine for all
                    runs[e, c].append(_child(e, path, cache))
    finally:
        if cache_dir:
            shutil.rmtree(cache_dir, ignore_errors=True)
    rows = []
    for (e, c), rs in runs.items():
        cold = [r["cold_s"] for r in rs]
        rows.append(
            {
                "entry": e,
                "code": c,
                "cold_s": min(cold),
                "cold_max_s": max(cold),
                "warm_s": min(r["warm_s"] for r in rs),
                "compiles": rs[0]["compiles"],
                "import_s": min(r["import_s"] for r in rs),
                "repeats": len(rs),
            }
        )
    base = {r["entry"]: r["cold_s"] for r in rows if r["code"].startswith("baseline")}
    plain = {r["entry"]: r["cold_s"] for r in rows if r["code"] == "current"}
    for row in rows:
        b = base.get(row["entry"])
        row["speedup_vs_baseline"] = b / row["cold_s"] if b else None
        if row["code"] == "current, persistent cache":
            row["speedup_vs_no_cache"] = plain[row["entry"]] / row["cold_s"]
    C.print_table(
        rows,
        ["entry", "code", "cold_s", "cold_max_s", "warm_s", "compiles", "import_s"],
        "first call in a fresh process (min over repeats)",
    )
    json_path, png_path = C.output_paths(args, "startup")
    C.write_json(
        json_path,
        {
            "benchmark": "startup",
            "quick": args.quick,
            "baseline": args.baseline,
            "persistent_cache": args.persistent_cache,
            "env": C.environment(),
            "rows": rows,
        },
    )
    fig, ax = C.plt.subplots(figsize=(8, 0.45 * len(entries) + 1.5), constrained_layout=True)
    y = np.arange(len(entries))
    h = 0.8 / len(codes)
    for i, c in enumerate(codes):
        vals = [next(r for r in rows if r["entry"] == e and r["code"] == c) for e in entries]
        bars = ax.barh(y + i * h, [v["cold_s"] for v in vals], height=h, label=c)
        for b, v in zip(bars, vals, strict=True):
            ax.text(b.get_width(), b.get_y() + h / 2, f" {v['compiles']}", va="center", fontsize=7)
    ax.set_yticks(y + h * (len(codes) - 1) / 2, entries, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("first call in a fresh process (s); labels: XLA programs compiled (or loaded)")
    ax.legend(fontsize=8)
    C.save_figure(fig, png_path)


if __name__ == "__main__":
    main()
