"""Figure tables generated from the benchmark results, written between markers in the docs.

``python benchmarks/report.py`` reads ``benchmarks/results/*.json`` and rewrites every
block

    <!-- report:NAME -->
    ...
    <!-- /report:NAME -->

found in ``README.md``, ``benchmarks/README.md``, ``docs/performance.md`` and
``docs/integrators.md`` with the table ``NAME`` built from those results (`BLOCKS` lists
the names). ``--check`` writes
nothing: it prints a unified diff of each file whose blocks are stale and exits 1 if
any is. ``--root DIR`` reads and writes another checkout of the repository.

Every figure is a ratio against a baseline measured in the same run, or a rate or a time
with its baseline's beside it. Where a JSON holds repeated rounds the table gives the
minimum and the range. A figure that no result holds is written "not measured", with
the script that would measure it. Each table names its source files. Plain Python:
no JAX, no NumPy, so the check costs CI a fraction of a second.

    python benchmarks/report.py            # rewrite the blocks
    python benchmarks/report.py --check    # exit 1 if a block is stale
"""

from __future__ import annotations

import argparse
import difflib
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = "benchmarks/results"
FILES = ("README.md", "benchmarks/README.md", "docs/performance.md", "docs/integrators.md")
BLOCK = re.compile(r"<!-- report:(?P<name>[\w-]+) -->(?P<body>.*?)<!-- /report:(?P=name) -->", re.S)
OPEN = re.compile(r"<!-- (/?)report:([\w-]+) -->")
NOT_MEASURED = "not measured"


# ---------------------------------------------------------------------------------------
# Reading the results


class Results:
    """The JSON files of one results folder, read once each."""

    def __init__(self, folder: Path):
        self.folder = folder
        self._cache: dict[str, dict | None] = {}

    def get(self, name: str) -> dict | None:
        """The parsed ``name`` (a file name in the folder), or None if it is missing."""
        if name not in self._cache:
            path = self.folder / name
            self._cache[name] = json.loads(path.read_text()) if path.is_file() else None
        return self._cache[name]

    def glob(self, pattern: str) -> list[str]:
        """File names matching ``pattern``, sorted, without smoke runs or partial files."""
        return sorted(
            p.name
            for p in self.folder.glob(pattern)
            if not p.name.endswith(("-quick.json", ".partial.json"))
        )

    def family(self, stem: str) -> list[str]:
        """``<stem>.json`` and ``<stem>-*.json``: CPU results first, then each GPU's (by
        device name), a script's own output name (``<stem>.json``, ``<stem>-gpu*.json``)
        before the variants."""

        def key(n):
            d = self.get(n)
            own = n == f"{stem}.json" or n.startswith(f"{stem}-gpu")
            return (is_gpu(d), device(d) if is_gpu(d) else "", not own, n)

        return sorted(self.glob(f"{stem}.json") + self.glob(f"{stem}-*.json"), key=key)

    def gpu(self, stem: str) -> list[str]:
        """``stem``'s GPU results (``<stem>-gpu.json``, ``<stem>-gpu-<device>.json``),
        ordered by device name."""
        names = [n for n in self.glob(f"{stem}-gpu*.json") if is_gpu(self.get(n))]
        return sorted(names, key=lambda n: device(self.get(n)))


def env(d: dict) -> dict:
    return d.get("env") or d.get("environment") or {}


def is_gpu(d: dict | None) -> bool:
    return d is not None and env(d).get("backend") not in (None, "cpu")


def device(d: dict) -> str:
    """The device a result was measured on, as its JSON names it."""
    e = env(d)
    if e.get("backend") in (None, "cpu"):
        return f"CPU, {e['cpu_count']} cores" if e.get("cpu_count") else "CPU"
    return e.get("device_kind") or e.get("backend", "?").upper()


def files(names) -> str:
    """The result files, as paths from the repository's root."""
    return ", ".join(f"`{RESULTS}/{n}`" for n in dict.fromkeys(n for n in names if n))


def sources(names) -> str:
    return f"Source: {files(names)}." if any(names) else ""


# ---------------------------------------------------------------------------------------
# Formatting (deterministic: fixed significant figures, no locale)


def x(r) -> str:
    """A ratio: 0.277x, 4.12x, 20.0x, 287x."""
    if r is None:
        return "–"
    if r >= 99.95:
        return f"{r:.0f}x"
    if r >= 9.995:
        return f"{r:.1f}x"
    if r >= 0.0995:
        return f"{r:.2f}x"
    return f"{r:.2g}x"


def sig3(v: float) -> str:
    """Three significant figures, trailing zeros kept: 0.500, 22.0, 158, 1,234."""
    if v >= 999.5:
        return f"{v:,.0f}"
    return f"{v:#.3g}".rstrip(".")


def _unit(s: float) -> tuple[float, str]:
    if s < 1e-5:
        return 1e6, "µs"
    if s < 1:
        return 1e3, "ms"
    return 1.0, "s"


def dur(s) -> str:
    """A time: µs below 10 µs, ms below 1 s, s above, three significant figures."""
    if s is None:
        return "–"
    k, unit = _unit(s)
    return f"{sig3(s * k)} {unit}"


def num(v) -> str:
    """A setting as written in code: 1e-8, 0.001, 2.5."""
    m = re.fullmatch(r"(-?[\d.]+)e([+-])0*(\d+)", f"{v:g}")
    if m is None:
        return f"{v:g}"
    return f"{m[1]}e{'-' if m[2] == '-' else ''}{m[3]}"


def rate(v) -> str:
    """A rate in scientific notation: 1.40e7."""
    if v is None:
        return "–"
    m, e = f"{v:.2e}".split("e")
    return f"{m}e{int(e)}"


def count(v) -> str:
    return "–" if v is None else f"{v:,.0f}"


def sci(v) -> str:
    """A small error: 6.9e-9."""
    if v is None:
        return "–"
    m, e = f"{v:.1e}".split("e")
    return f"{m}e{int(e)}"


def span(values) -> str:
    """The minimum and, where values differ, the range: ``41.8 ms (41.8–42.2 ms)``."""
    values = [v for v in values if v is not None]
    if not values:
        return "–"
    lo, hi = min(values), max(values)
    if dur(lo) == dur(hi):
        return dur(lo)
    k, unit = _unit(hi)
    return f"{dur(lo)} ({sig3(lo * k)}–{sig3(hi * k)} {unit})"


def table(header: list[str], rows: list[list[str]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(row) + " |" for row in rows]
    return out


def not_measured(script: str, where: str = "") -> str:
    return f"{NOT_MEASURED} (`benchmarks/{script}`{where})"


# ---------------------------------------------------------------------------------------
# The blocks: each returns the Markdown between its markers.

BLOCKS = {}


def block(name):
    def register(fn):
        BLOCKS[name] = fn
        return fn

    return register


def _lie_methods(scene: dict) -> list[str]:
    return list(dict.fromkeys(p["method"] for p in scene["points"] if p["family"] == "lie"))


def _single(d):
    at = d["scenes"]["seed"]["at_1e-8"]
    lie = [m for m in _lie_methods(d["scenes"]["seed"]) if at[m]["vs_tsit5"] is not None]
    r, t, s = at.get("RKMK4"), at["diffrax Tsit5"], at["SciPy RK45"]
    if r is None or r["vs_tsit5"] is None:
        return None
    best = max(lie, key=lambda m: at[m]["vs_tsit5"])
    return (
        f"RKMK4 **{x(r['vs_tsit5'])}** diffrax Tsit5, **{x(r['vs_rk45'])}** SciPy RK45 "
        f"({dur(r['run_s'])} against {dur(t['run_s'])} and {dur(s['run_s'])}); "
        f"{best} {x(at[best]['vs_tsit5'])} and {x(at[best]['vs_rk45'])}"
    )


def _batch(d):
    eq = d.get("equal_accuracy")
    if not eq or "RKMK4 default" not in eq:
        return None
    r, t = eq["RKMK4 default"], eq["diffrax Tsit5"]
    best = eq["best"]["method"]
    return (
        f"RKMK4 **{x(eq['speedup_over_tsit5']['RKMK4 default'])}** vmapped Tsit5: "
        f"{rate(r['body_steps_per_s'])} against {rate(t['body_steps_per_s'])} body-steps/s; "
        f"{best.split(' ')[0].replace('-cayley', ' Cayley')} {x(eq['best']['speedup_over_tsit5'])}"
    )


def _sweep_rows(d):
    """``throughput.py``'s batch-size rows, unless this JSON borrowed another run's."""
    sw = d.get("sweep")
    if not sw or "from" in sw:
        return []
    return sw["rows"]


def _peak(d):
    rows = [r for r in _sweep_rows(d) if r["dtype"] == "float32"]
    if not rows:
        return None
    b = max(r["batch"] for r in rows)
    at = {r["method"]: r for r in rows if r["batch"] == b}
    if "RKMK4" not in at or "diffrax RK4" not in at:
        return None
    r, rk4 = at["RKMK4"]["body_steps_per_s"], at["diffrax RK4"]["body_steps_per_s"]
    return (
        f"RKMK4 **{rate(r)}** body-steps/s over {count(b)} runs, "
        f"{x(r / rk4)} vmapped diffrax RK4 ({rate(rk4)})"
    )


def _tune_row(d, variant, batch, n_steps):
    for r in d["rows"]:
        if (r["variant"], r["batch"], r["n_steps"]) == (variant, batch, n_steps):
            return r
    return None


def _gradient(d):
    g = _tune_row(d, "reverse (default)", 256, 1000)
    f = _tune_row(d, "forward pass", 256, 1000)
    if g is None or f is None:
        return None
    return (
        f"`grad` **{x(g['time_ratio'])}** its forward pass "
        f"({dur(g['seconds'])} against {dur(f['seconds'])})"
    )


def _sweep(d):
    rows = {r["dtype"]: r for r in d["rows"]}
    r64, r32 = rows.get("float64"), rows.get("float32")
    if r64 is None:
        return None
    out = f"**{count(r64['runs_per_second'])} runs/s** in float64"
    if r32 is not None:
        ratio = r32["runs_per_second"] / r64["runs_per_second"]
        out += f"; float32 {count(r32['runs_per_second'])} ({x(ratio)})"
    return out


def _difftune(d):
    loop, wall = d["tune_loop_without_compile_s"], d["tune_wall_s"]
    mode = min(loop, key=loop.get)
    it = d["iteration_over_forward"][f"value and gradient, {mode} mode"]
    fwd = d["timings"]["forward pass"]["run_s"]
    return (
        f"**{dur(loop[mode])}** without compilation, {dur(wall[mode])} with ({mode} mode); "
        f"an iteration {x(it)} a forward pass ({dur(fwd)})"
    )


# (label, script, file stem, cell): the rows of the README's "How fast" table. A callable
# label is given the CPU's JSON (the GPU's where the CPU has none).
HOW_FAST = [
    (
        "One run, seed scenario, 10 s, attitude error 1e-8 (float64)",
        "work_precision.py",
        "work_precision",
        _single,
    ),
    (
        lambda d: (
            f"A batch: `vmap` of {d['equal_accuracy']['batch']} runs, attitude error 1e-8 (float64)"
        ),
        "throughput.py",
        "throughput",
        _batch,
    ),
    ("A large batch, 100 steps (float32)", "throughput.py", "throughput", _peak),
    (
        "A gradient: mean tracking cost over 256 runs, 1000 steps (float64)",
        "tune.py",
        "tune",
        _gradient,
    ),
    (
        lambda d: "A sweep: {} × {} gains × {} attitudes, {} runs of {} steps".format(
            *d["rows"][0]["grid"],
            d["rows"][0]["n_attitudes"],
            count(d["rows"][0]["n_runs"]),
            d["rows"][0]["n_steps"],
        ),
        "sweep.py",
        "sweep",
        _sweep,
    ),
    (
        "DiffTune's quadrotor example: 100 iterations of `tune`, 12 gains, 4000 steps",
        "difftune.py",
        "difftune",
        _difftune,
    ),
]


def _how_fast_gpu(R: Results) -> tuple[str | None, dict[str, str]]:
    """The GPU of the "How fast" column: the one with the most rows measured, then the
    latest measurement."""
    by_device: dict[str, dict[str, str]] = {}
    for stem in dict.fromkeys(row[2] for row in HOW_FAST):
        for name in R.gpu(stem):
            by_device.setdefault(device(R.get(name)), {}).setdefault(stem, name)
    if not by_device:
        return None, {}

    def key(dev):
        files = by_device[dev]
        return (len(files), max(env(R.get(n)).get("date", "") for n in files.values()))

    dev = max(sorted(by_device), key=key)
    return dev, by_device[dev]


@block("how-fast")
def how_fast(R: Results) -> str:
    gpu, gpu_files = _how_fast_gpu(R)
    cpu_names = [f"{row[2]}.json" for row in HOW_FAST]
    cpus = sorted({device(R.get(n)) for n in cpu_names if R.get(n) is not None})
    cpu_head = cpus[0] if len(cpus) == 1 else "CPU"
    rows, used_cpu, used_gpu = [], [], []
    for label, script, stem, cell in HOW_FAST:
        if callable(label):
            first = R.get(f"{stem}.json") or R.get(gpu_files.get(stem, ""))
            label = label(first) if first is not None else script
        cells = []
        for name, used, where in (
            (f"{stem}.json", used_cpu, ""),
            (gpu_files.get(stem), used_gpu, " on a GPU"),
        ):
            d = R.get(name) if name else None
            text = cell(d) if d is not None else None
            if text is None:
                cells.append(not_measured(script, where))
            else:
                cells.append(text)
                used.append(name)
        rows.append([label, *cells])
    lines = table(["", cpu_head, f"GPU: {gpu}" if gpu else "GPU"], rows)
    lines += ["", f"Sources: CPU {files(used_cpu) or 'none'}; GPU {files(used_gpu) or 'none'}."]
    return "\n".join(lines) + "\n"


@block("single-run")
def single_run(R: Results) -> str:
    d = R.get("work_precision.json")
    if d is None:
        return not_measured("work_precision.py") + "\n"
    scenes = d["scenes"]
    names = list(scenes)
    header = ["method"]
    for s in names:
        label = s.replace("_", " ")
        header += [f"{label}: time", "evaluations", "× Tsit5", "× SciPy RK45"]
    rows = []
    for m in scenes[names[0]]["at_1e-8"]:
        row = [m]
        for s in names:
            a = scenes[s]["at_1e-8"].get(m, {})
            ev = a.get("fevals")
            row += [
                dur(a.get("run_s")),
                "–" if ev is None else f"{ev:.0f}",
                x(a.get("vs_tsit5")),
                x(a.get("vs_rk45")),
            ]
        rows.append(row)
    lines = table(header, rows)
    lines += [
        "",
        f"{device(d)}, float64. Time per run at final attitude error "
        f"{num(d['target'])} (log-log interpolation of each method's curve); ×: the baseline's "
        "time over this method's, in the same run. –: the method's runs do not reach "
        f"{num(d['target'])} in the range measured. {sources(['work_precision.json'])}",
    ]
    return "\n".join(lines) + "\n"


@block("single-run-errors")
def single_run_errors(R: Results) -> str:
    """The errors the single-run table leaves out: the low-order methods' best, and how far
    each family ends from the group."""
    d = R.get("work_precision.json")
    if d is None:
        return not_measured("work_precision.py") + "\n"
    scenes = d["scenes"]

    def finest(scene: str, method: str) -> dict:
        points = [p for p in scenes[scene]["points"] if p["method"] == method]
        return max(points, key=lambda p: p["value"])

    lgvi = [finest(s, "LGVI") for s in ("seed", "free_body")]
    euler = [finest(s, "LieEuler") for s in ("seed", "free_body")]
    rk4 = [p for p in scenes["seed"]["points"] if p["method"] == "diffrax RK4"]
    rk4 = min(rk4, key=lambda p: abs(p["value"] - 1000))
    lie = [p["orth_err"] for sc in scenes.values() for p in sc["points"] if p["family"] == "lie"]
    target = num(d["target"])
    steps = " and ".join(dict.fromkeys(count(p["value"]) for p in euler))
    return (
        f"`LGVI` (order 2) reaches {sci(lgvi[0]['att_err'])} at {count(lgvi[0]['value'])} "
        f"steps on the seed and {sci(lgvi[1]['att_err'])} at {count(lgvi[1]['value'])} on "
        f"the free body, and `LieEuler` {sci(euler[0]['att_err'])} and "
        f"{sci(euler[1]['att_err'])} at {steps} steps: neither crosses "
        f"{target} in the range run. The ambient methods drift off the group to the level "
        f"of their error (diffrax RK4: `||R^T R - I||` {sci(rk4['orth_err'])} after "
        f"{count(rk4['value'])} steps on the seed); the Lie-group methods end at "
        f"{sci(min(lie))} to {sci(max(lie))}. {sources(['work_precision.json'])}\n"
    )


def _adaptive_name(m: str) -> str:
    family, _, name = m.partition("-")
    name = name.replace("-cayley", ", Cayley coordinates")
    return f"diffrax {name} (ambient)" if family == "ambient" else name


@block("adaptive")
def adaptive(R: Results) -> str:
    d = R.get("adaptive.json")
    if d is None:
        return not_measured("adaptive.py") + "\n"
    rows = []
    for a in d["at_target"]:
        rows.append(
            [
                _adaptive_name(a["method"]),
                num(a["matched_tol"]),
                sci(a["matched_error"]),
                dur(a["matched_run_s"]),
                f"{a['matched_steps']} ({a['matched_rejected']})",
                f"{a['matched_fevals']}",
                sci(a["matched_orthogonality"]),
                x(a["tsit5_matched_time_over_this"]),
                x(a["tsit5_time_over_this"]),
            ]
        )
    t = d["target_attitude_error"]
    lines = table(
        [
            "method",
            "tolerance",
            "attitude error",
            "time",
            "steps (rejected)",
            "evaluations",
            "‖RᵀR − I‖",
            "Tsit5 time / this",
            f"the same at {num(t)}",
        ],
        rows,
    )
    lines += [
        "",
        f"{device(d)}, float64, {d['scene']} scenario, {d['duration_s']:g} s, "
        f"`diffeqsolve` with `PIDController`; the last column interpolates each method's "
        f"time to attitude error {num(t)}. {sources(['adaptive.json'])}",
    ]
    return "\n".join(lines) + "\n"


def _variant(label: str) -> str:
    """A label of ``throughput.py``'s equal-accuracy part, in words."""
    if label == "RKMK4":
        return "RKMK4, array program forced"
    name, _, how = label.partition(" ")
    name = name.replace("-cayley", " Cayley")
    if how == "default":
        return f"{name} (default program)"
    if how == "scalarized":
        return f"{name}, scalarized"
    return name if not how else f"{name} {how}"


def _throughput_files(R: Results) -> list[str]:
    return R.family("throughput")


def _column(d: dict, devices: int = 1) -> str:
    col = device(d)
    return col + (f", sharded over {devices} devices" if devices > 1 else "")


@block("batch")
def batch(R: Results) -> str:
    names = [n for n in _throughput_files(R) if "equal_accuracy" in R.get(n)]
    if not names:
        return not_measured("throughput.py", " --equal-only") + "\n"
    eqs = {n: R.get(n)["equal_accuracy"] for n in names}
    variants = list(dict.fromkeys(v for n in names for v in eqs[n]["variants"]))
    steps = {}
    for n in names:
        for k, v in eqs[n]["n_steps"].items():
            steps.setdefault(k, v)
    rows = []
    for v in [*variants, "diffrax Tsit5"]:
        row = [_variant(v) if v != "diffrax Tsit5" else "diffrax Tsit5, vmapped (the baseline)"]
        if v == "diffrax Tsit5":
            row.append("adaptive")
        else:
            row.append(f"{steps.get(v.split(' ')[0], '–')}")
        for n in names:
            e = eqs[n].get(v)
            if e is None:
                row.append(NOT_MEASURED)
                continue
            ratio = 1.0 if v == "diffrax Tsit5" else eqs[n]["speedup_over_tsit5"][v]
            row.append(f"**{x(ratio)}**, {rate(e['body_steps_per_s'])}")
        rows.append(row)
    header = ["program", "steps"] + [_column(R.get(n), eqs[n].get("devices", 1)) for n in names]
    b = sorted({eqs[n]["batch"] for n in names})
    lines = table(header, rows)
    lines += [
        "",
        f"{' and '.join(str(v) for v in b)} seed runs of 10 s from random attitudes, float64, "
        "each program at the step count (Tsit5: the tolerance) that reaches final attitude "
        "error 1e-8; each cell: Tsit5's time over the program's, and body-steps/s "
        f"(Tsit5: accepted steps). {sources(names)}",
    ]
    return "\n".join(lines) + "\n"


@block("throughput")
def throughput(R: Results) -> str:
    names = [n for n in _throughput_files(R) if _sweep_rows(R.get(n))]
    if not names:
        return not_measured("throughput.py", " --sweep-only") + "\n"
    largest, at = {}, {}
    for n in names:
        rows = _sweep_rows(R.get(n))
        largest[n] = max(r["batch"] for r in rows)
        at[n] = {(r["method"], r["dtype"]): r for r in rows if r["batch"] == largest[n]}
    keys = list(dict.fromkeys(k for n in names for k in at[n]))
    keys.sort(key=lambda k: k[1] != "float32")  # stable: float32 first, JSON order within
    rows = []
    for method, dtype in keys:
        label = "RKMK4, array program forced" if method == "RKMK4 array" else method
        if not method.startswith("diffrax"):
            label += "" if method == "RKMK4 array" else " (default program)"
        row = [label, dtype]
        for n in names:
            r = at[n].get((method, dtype))
            base = at[n].get(("diffrax Tsit5", dtype))
            if r is None:
                row.append(NOT_MEASURED)
            elif base is None or method == "diffrax Tsit5":
                row.append(rate(r["body_steps_per_s"]))
            else:
                ratio = r["body_steps_per_s"] / base["body_steps_per_s"]
                row.append(f"{rate(r['body_steps_per_s'])} ({x(ratio)})")
        rows.append(row)
    header = ["method", "dtype"] + [f"{device(R.get(n))}, {count(largest[n])} runs" for n in names]
    n_steps = sorted({R.get(n)["sweep"]["n_steps"] for n in names})
    lines = table(header, rows)
    lines += [
        "",
        f"Body-steps/s of `vmap(simulate)` over the largest batch each device ran, "
        f"{' and '.join(str(s) for s in n_steps)} steps of the seed scenario from random "
        "attitudes; in brackets, the ratio to vmapped diffrax Tsit5 in the same run (Tsit5 "
        "counts its accepted steps, at rtol = atol = 1e-8 in float64 and 1e-5 in float32: "
        f"not at equal accuracy). {sources(names)}",
    ]
    return "\n".join(lines) + "\n"


def _tune_columns(R: Results, stems):
    """(file, batch, n_steps) of every ``tune.py`` result, CPU first, then GPUs."""
    cols = []
    for stem in stems:
        for n in [f"{stem}.json", *R.gpu(stem)]:
            d = R.get(n)
            if d is None:
                continue
            combos = dict.fromkeys((r["batch"], r["n_steps"]) for r in d["rows"])
            cols += [(n, b, s) for b, s in sorted(combos)]
    return cols


def _tune_table(R: Results, stems) -> tuple[list[str], list[str]]:
    cols = _tune_columns(R, stems)
    names = list(dict.fromkeys(c[0] for c in cols))
    variants = list(dict.fromkeys(r["variant"] for n in names for r in R.get(n)["rows"]))
    rows = []
    for v in variants:
        row = [v]
        for n, b, s in cols:
            r = _tune_row(R.get(n), v, b, s)
            if r is None:
                row.append("–")
            elif v == "forward pass":
                row.append(dur(r["seconds"]))
            else:
                row.append(x(r["time_ratio"]))
        rows.append(row)
    header = ["variant"] + [f"{device(R.get(n))}, {b} runs, {s} steps" for n, b, s in cols]
    return table(header, rows), names


@block("gradients")
def gradients(R: Results) -> str:
    lines, names = _tune_table(R, ["tune"])
    if not names:
        return not_measured("tune.py") + "\n"
    lines += [
        "",
        "The mean tracking cost of the seed scenario over a batch of random attitudes, as a "
        "function of (k_R, k_Omega), RKMK4, dt = 1e-2, float64: the forward pass's time, "
        "and each variant's time over that forward pass, measured in the same run. "
        f"{sources(names)}",
    ]
    return "\n".join(lines) + "\n"


@block("trajectory-cost")
def trajectory_cost(R: Results) -> str:
    lines, names = _tune_table(R, ["tune-trajectory"])
    if not names:
        return not_measured("tune.py", " --cost trajectory") + "\n"
    lines += [
        "",
        "A user's own cost on saved runs (`tracking_cost(simulate(...))`, every state "
        "saved), RKMK4, float64: the forward pass's time and each derivative's time over it. "
        f"{sources(names)}",
    ]
    return "\n".join(lines) + "\n"


@block("allocator")
def allocator(R: Results) -> str:
    d = R.get("allocator.json")
    if d is None:
        return not_measured("allocator.py") + "\n"
    settings = list(d["settings"])
    progs = list(
        dict.fromkeys((r["cost"], r["derivative"], r["batch"], r["n_steps"]) for r in d["rows"])
    )
    by = {
        (r["cost"], r["derivative"], r["batch"], r["n_steps"], r["setting"]): r for r in d["rows"]
    }
    what = {
        "trajectory": "cost on saved runs",
        "expected": "`expected_cost`",
        "simulate": "`vmap(simulate)`",
    }
    rows = []
    for p in progs:
        cost, deriv, b, s = p
        row = [f"{what.get(cost, cost)}, {b} runs, {s} steps: {deriv}"]
        for st in settings:
            r = by.get((*p, st))
            if r is None:
                row.append(NOT_MEASURED)
                continue
            cell = span(r.get("rounds") or [r["seconds"]])
            if deriv != "forward":
                cell += f", {x(r['forward_ratio'])} the forward pass"
            row.append(cell)
        first, last = by.get((*p, settings[0])), by.get((*p, settings[-1]))
        row.append(x(last["seconds"] / first["seconds"]) if first and last else "–")
        rows.append(row)
    lines = table(["program", *settings, f"{settings[-1]} / {settings[0]}"], rows)
    kept = ", ".join(f"`{k}={v}`" for k, v in d["settings"][settings[-1]].items())
    lines += [
        "",
        f"{device(d)}, float64, RKMK4, each setting in its own child processes, rounds "
        f"alternated: the fastest call, and the range over rounds. {settings[-1]}: {kept}. "
        f"{sources(['allocator.json'])}",
    ]
    return "\n".join(lines) + "\n"


@block("sweep")
def sweep(R: Results) -> str:
    names = R.family("sweep")
    if not names:
        return not_measured("sweep.py") + "\n"
    rows = []
    for n in names:
        d = R.get(n)
        by = {r["dtype"]: r for r in d["rows"]}
        for dtype, r in by.items():
            program = {True: "scalarized", False: "array"}.get(r.get("scalarize"), "default")
            ratio = (
                x(1.0)
                if dtype == "float64"
                else x(r["runs_per_second"] / by["float64"]["runs_per_second"])
                if "float64" in by
                else "–"
            )
            rows.append(
                [
                    device(d),
                    program,
                    count(r["chunk_size"]),
                    dtype,
                    f"**{count(r['runs_per_second'])}**",
                    ratio,
                    dur(r.get("first_sweep_s")),
                    dur(r["first_chunk_with_compile_s"]),
                    f"`{n}`",
                ]
            )
    lines = table(
        [
            "device",
            "program",
            "chunk",
            "dtype",
            "runs/s",
            "× float64",
            "first sweep",
            "compile + first chunk",
            "source",
        ],
        rows,
    )
    r0 = R.get(names[0])["rows"][0]
    g = r0["grid"]
    lines += [
        "",
        f"`so3jax.sweep` over a {g[0]} × {g[1]} gain grid × {r0['n_attitudes']} attitudes "
        f"({count(r0['n_runs'])} runs of {r0['n_steps']} steps, seed scenario, "
        f"{r0['method']}): runs/s of a compiled sweep, float32 against float64 in the same "
        "run; the first sweep compiles its re-runs of runs past the step limit. Files in "
        f"`{RESULTS}/`.",
    ]
    return "\n".join(lines) + "\n"


def _spread(walls: list) -> str:
    """`` (fastest–slowest)`` of several timed runs; nothing for one."""
    return f" ({dur(min(walls))}–{dur(max(walls))})" if len(walls) > 1 else ""


@block("difftune")
def difftune(R: Results) -> str:
    d = R.get("difftune.json")
    if d is None:
        return not_measured("difftune.py") + "\n"
    t, it = d["timings"], d["iteration_over_forward"]
    rows = [[k, dur(v["run_s"]), x(it[k]), dur(v["compile_s"])] for k, v in t.items()]
    n = d["n_iter"]
    for mode in d["tune_wall_s"]:
        spread = _spread(d.get("tune_walls_s", {}).get(mode, []))
        rows.append(
            [
                f"{n} iterations, {mode} mode: with compilation / loop alone / "
                f"{n} × the fastest iteration",
                f"{dur(d['tune_wall_s'][mode])}{spread} / "
                f"{dur(d['tune_loop_without_compile_s'][mode])}"
                f" / {dur(d['n_iter_times_fastest_iteration_s'][mode])}",
                "",
                "",
            ]
        )
    fresh = d.get("tune_reverse_fresh_process_walls_s")
    if fresh:
        rows.append(
            [
                f"{n} iterations, reverse mode, in a fresh process (tracing included)",
                f"{dur(min(fresh))}{_spread(fresh)}",
                "",
                "",
            ]
        )
    rmse = d["rmse_history"]
    rows.append(
        [
            f"RMSE of the position error, before and after {n} iterations",
            f"{rmse[0]:.4f} m → {rmse[-1]:.4f} m",
            x(rmse[-1] / rmse[0]),
            "",
        ]
    )
    lines = table(["", "time", "× forward pass", "compile"], rows)
    lines += [
        "",
        f"{device(d)}, float64, {d['method']}, {d['n_steps']} steps of {num(d['dt'] * 1e3)} ms, "
        f"projected gradient descent (learning rate {num(d['learning_rate'])}, gains at least "
        f"{num(d['lower_bound'])}). {sources(['difftune.json'])}",
    ]
    return "\n".join(lines) + "\n"


@block("adjoint")
def adjoint(R: Results) -> str:
    d = R.get("adjoint.json")
    if d is None:
        return not_measured("adjoint.py") + "\n"
    by = {(r["workload"], r["saved"]): r for r in d["rows"]}
    rows = []
    for workload in dict.fromkeys(r["workload"] for r in d["rows"]):
        res, ck = by[(workload, "residuals")], by[(workload, "checkpoints")]
        rows.append(
            [
                workload,
                span(res["first_s_rounds"]),
                span(ck["first_s_rounds"]),
                x(ck["first_s"] / res["first_s"]),
                span(res["run_s_rounds"]),
                span(ck["run_s_rounds"]),
                x(ck["run_s"] / res["run_s"]),
            ]
        )
    header = [
        "",
        "first call: residuals",
        "checkpoints",
        "checkpoints / residuals",
        "later calls: residuals",
        "checkpoints",
        "checkpoints / residuals",
    ]
    lines = table(header, rows)
    lines += [
        "",
        f"{device(d)}, float64, DiffTune's quadrotor, {d['n_steps']} steps, "
        f"`value_and_grad` through the 12 gains; each figure in a fresh interpreter, the "
        f"fastest of {d['rounds']} rounds with the range. {sources(['adjoint.json'])}",
    ]
    return "\n".join(lines) + "\n"


@block("startup")
def startup(R: Results) -> str:
    names = [n for n in ["startup.json", *R.gpu("startup")] if R.get(n) is not None]
    if not names:
        return not_measured("startup.py") + "\n"
    entries = list(dict.fromkeys(r["entry"] for n in names for r in R.get(n)["rows"]))
    header = ["first call of"]
    for n in names:
        dev = device(R.get(n))
        header += [f"{dev}: cold (range); warm", f"{dev}: cold, persistent cache"]
    rows = []
    for e in entries:
        row = [e]
        for n in names:
            by = {r["code"]: r for r in R.get(n)["rows"] if r["entry"] == e}
            plain, cached = by.get("current"), by.get("current, persistent cache")
            if plain is None:
                row.append(NOT_MEASURED)
            else:
                row.append(
                    f"{span([plain['cold_s'], plain['cold_max_s']])}; {dur(plain['warm_s'])}"
                )
            if cached is None:
                row.append(NOT_MEASURED)
            else:
                row.append(
                    f"{dur(cached['cold_s'])} ({x(cached.get('speedup_vs_no_cache'))} faster)"
                )
        rows.append(row)
    lines = table(header, rows)
    lines += [
        "",
        "Each entry in a fresh process: the first (cold) call with its compilations, the "
        "fastest and the range over repeats, then the same call again (warm); with JAX's "
        f"persistent compilation cache filled by an earlier process. {sources(names)}",
    ]
    return "\n".join(lines) + "\n"


@block("integrators")
def integrators(R: Results) -> str:
    d = R.get("integrators.json")
    if d is None:
        return not_measured("integrators.py") + "\n"
    ms = d["methods"]
    base = next((m for m in ms if m["method"] == "RKMK4"), ms[0])
    rows = [
        [
            m["method"],
            str(m["order"]),
            f"{m['us_per_step']:.3g} µs",
            x(m["us_per_step"] / base["us_per_step"]),
            rate(m["batch_body_steps_per_s"]),
            x(m["batch_body_steps_per_s"] / base["batch_body_steps_per_s"]),
            dur(m["compile_s"]),
            dur(m["batch_compile_s"]),
        ]
        for m in ms
    ]
    b = ms[0]["batch"]
    lines = table(
        [
            "method",
            "order",
            "one run: per step",
            f"× {base['method']}",
            f"{b} runs: body-steps/s",
            f"× {base['method']}",
            "compile (one run)",
            f"compile ({b} runs)",
        ],
        rows,
    )
    meta = d["meta"]
    lines += [
        "",
        f"Free body, {meta['dtype']}, dt = {num(meta['dt'])}: one run of {meta['n_single']:,} "
        f"steps, and a vmapped batch of {b} runs of {meta['n_batch_steps']} steps; "
        f"{device(d)}. {sources(['integrators.json'])}",
    ]
    return "\n".join(lines) + "\n"


@block("shared-reference")
def shared_reference(R: Results) -> str:
    d = R.get("shared_reference.json")
    if d is None:
        return not_measured("shared_reference.py") + "\n"
    kinds = list(dict.fromkeys(r["batch"] for r in d["rows"]))
    by = {(r["batch"], r["Rd"]): r for r in d["rows"]}
    rows = []
    for k in kinds:
        per, shared = by.get((k, "per run")), by.get((k, "shared"))
        if per is None or shared is None:
            continue
        rows.append(
            [
                f"{k}, {shared['B']} runs of {shared['n_steps']} steps",
                rate(per["body_steps_per_s"]),
                rate(shared["body_steps_per_s"]),
                x(shared["body_steps_per_s"] / per["body_steps_per_s"]),
            ]
        )
    lines = table(["batch", "Rd per run: body-steps/s", "Rd shared", "shared / per run"], rows)
    lines += [
        "",
        f"{device(d)}, float64, {d['method']}, dt = {num(d['dt'])}: the reference attitude "
        f"integrated once for the batch against once per run. {sources(['shared_reference.json'])}",
    ]
    return "\n".join(lines) + "\n"


@block("compile")
def compile_times(R: Results) -> str:
    """Compile times of the main programs, with the baseline's compile beside each."""
    cols = [("CPU", "")]
    gpus = sorted(
        {device(R.get(n)) for stem in ("throughput", "tune", "sweep") for n in R.gpu(stem)}
    )
    cols += [(g, g) for g in gpus]
    used = []

    def pick(stem, dev):
        if not dev:
            return f"{stem}.json" if R.get(f"{stem}.json") is not None else None
        return next((n for n in R.gpu(stem) if device(R.get(n)) == dev), None)

    def one_run(dev):
        n = pick("work_precision", dev)
        if n is None:
            return None
        at = R.get(n)["scenes"]["seed"]["at_1e-8"]
        return n, f"{dur(at['RKMK4']['compile_s'])} (Tsit5 {dur(at['diffrax Tsit5']['compile_s'])})"

    def vmapped(dev):
        n = pick("throughput", dev)
        eq = R.get(n).get("equal_accuracy") if n else None
        if not eq or "RKMK4 default" not in eq:
            return None
        c, t = eq["RKMK4 default"]["compile_s"], eq["diffrax Tsit5"]["compile_s"]
        return n, f"{dur(c)} (Tsit5 {dur(t)})"

    def grad(batch):
        def cell(dev):
            n = pick("tune", dev)
            d = R.get(n) if n else None
            g = _tune_row(d, "reverse (default)", batch, 1000) if d else None
            f = _tune_row(d, "forward pass", batch, 1000) if d else None
            if g is None or f is None:
                return None
            return n, f"{dur(g['compile_s'])} (forward pass {dur(f['compile_s'])})"

        return cell

    def sweep_chunk(dev):
        n = pick("sweep", dev)
        if n is None:
            return None
        r = {r["dtype"]: r for r in R.get(n)["rows"]}.get("float64")
        if r is None:
            return None
        return n, f"{dur(r['first_chunk_with_compile_s'])} (chunk of {count(r['chunk_size'])})"

    def difftune_(dev):
        n = pick("difftune", dev)
        if n is None:
            return None
        t = R.get(n)["timings"]
        parts = [
            f"{m}: {dur(t[f'value and gradient, {m} mode']['compile_s'])}"
            for m in ("forward", "reverse")
            if f"value and gradient, {m} mode" in t
        ]
        return n, "; ".join(parts) + f" (forward pass {dur(t['forward pass']['compile_s'])})"

    specs = [
        ("one run, RKMK4, seed at attitude error 1e-8", one_run),
        ("`vmap` of 4096 runs, RKMK4 (default program)", vmapped),
        ("`grad` over 16 runs, 1000 steps", grad(16)),
        ("`grad` over 256 runs, 1000 steps", grad(256)),
        ("`grad` over 4096 runs, 1000 steps", grad(4096)),
        ("a sweep: compile and first chunk, float64", sweep_chunk),
        ("DiffTune's value and gradient, 12 gains", difftune_),
    ]
    rows = []
    for label, fn in specs:
        row = [label]
        for _, dev in cols:
            got = fn(dev)
            if got is None:
                row.append(NOT_MEASURED)
            else:
                used.append(got[0])
                row.append(got[1])
        rows.append(row)
    cpu = next((device(R.get(n)) for n in used if not is_gpu(R.get(n))), "CPU")
    header = ["program", cpu, *gpus]
    lines = table(header, rows)
    lines += [
        "",
        "Lowering and XLA compilation of each program, with its baseline's in the same run "
        f"in brackets. {sources(used)}",
    ]
    return "\n".join(lines) + "\n"


def _middle_half(values: list[float]) -> tuple[float, float]:
    """The first and third quartiles (linear interpolation): a range that one call slowed by
    the machine's other load does not stretch."""
    v = sorted(values)

    def q(p):
        i = p * (len(v) - 1)
        lo = int(i)
        return v[lo] + (v[min(lo + 1, len(v) - 1)] - v[lo]) * (i - lo)

    return q(0.25), q(0.75)


def _ablation(d: dict, name: str) -> tuple[list[str], set[str]]:
    """One machine's ablation (``name``): its table and text, and the passes that buy less
    than 10 % on every workload there."""
    base, wl, configs = "all passes", list(d["workloads"]), list(d["configs"])
    by = {(r["config"], r["workload"]): r for r in d["rows"]}
    ratios: dict[str, dict[str, float]] = {}  # configuration -> workload -> ratio
    compiles: dict[str, dict[str, float]] = {}  # configuration -> workload -> compile ratio
    traces: dict[str, dict[str, float]] = {}  # configuration -> workload -> tracing ratio

    def cell(c, w):
        r, b = by.get((c, w)), by.get((base, w))
        if r is None or b is None:
            return NOT_MEASURED
        if c == base:
            lo, hi = _middle_half(r["rounds"])
            k, unit = _unit(hi)
            text = (
                f"{dur(r['run_s'])} ({sig3(lo * k)}–{sig3(hi * k)} {unit}), "
                f"compile {dur(r['compile_s'])}"
            )
            return text + (f" (tracing {dur(r['trace_s'])})" if "trace_s" in r else "")
        ratio = r["run_s"] / b["run_s"]
        # a program the pass leaves as it is: the pass buys nothing there, whatever the noise
        ratios.setdefault(c, {})[w] = 1.0 if r["same_program_as_base"] else ratio
        rounds = [t / u for t, u in zip(r["rounds"], b["rounds"], strict=True)]
        lo, hi = (x(v) for v in _middle_half(rounds))
        text = f"**{x(ratio)}**" + ("" if lo == hi else f" ({lo[:-1]}–{hi})")

        def apart(key):  # the ratio of the fastest, where every round with the pass off
            # took longer than every round with all passes (else noise: 1.0)
            rounds, base_rounds = r.get(f"{key}_rounds"), b.get(f"{key}_rounds")
            ratio = r[key] / b[key]
            if not (rounds and base_rounds) or min(len(rounds), len(base_rounds)) < 2:
                return ratio, 1.0  # one compilation each: its noise is not measured
            if min(rounds) <= max(base_rounds):
                return ratio, 1.0
            return ratio, ratio

        ratio_c, compiles.setdefault(c, {})[w] = apart("compile_s")
        text += f", compile {x(ratio_c)}"
        if "trace_s" in r and "trace_s" in b:
            ratio_t, traces.setdefault(c, {})[w] = apart("trace_s")
            text += f" (tracing {x(ratio_t)})"
        return text + (", same program" if r["same_program_as_base"] else "")

    rows = [[c, *(cell(c, w) for w in wl)] for c in configs]
    lines = table(["configuration", *(d["workloads"][w]["label"] for w in wl)], rows)
    rounds = min(len(r["rounds"]) for r in d["rows"])
    text = (
        f"{device(d)}, {d['dtype']}, {d['method']}. First row: the fastest call with every "
        "pass (in brackets the middle half of the calls) and its compile time; other rows: "
        "the fastest call with a pass off over that, in brackets the middle half of that "
        f"ratio over the rounds (at least {rounds}, the configurations alternated in each), "
        "and the fastest compilation over that of all passes (tracing and lowering included; "
        f"{d.get('compile_rounds', 1)} per configuration, alternated), in brackets the same "
        "for tracing and lowering alone (the engine's share of it). *Same program*: XLA "
        "compiled the very "
        'program of all passes (the difference is noise). "none" is every pass off; '
        '"autodiff" also differentiates with JAX alone (`program="autodiff"`, where the API '
        "takes a program)."
    )

    def same_program(key):  # ``key``'s ratios over the rows whose program is all passes'
        return [
            r[key] / by[(base, r["workload"])][key]
            for r in d["rows"]
            if r["config"] != base and r["same_program_as_base"] and (base, r["workload"]) in by
        ]

    same, same_c = same_program("run_s"), same_program("compile_s")
    if same:
        text += f" The rows of the same program measure the noise: {x(min(same))[:-1]}"
        text += f"–{x(max(same))}."
    if same_c:
        text += f" Their compile times, {x(min(same_c))[:-1]}–{x(max(same_c))}, measure the"
        text += " noise of compilation and the tracing a pass changes without changing the program."
    passes = [p for p in d["passes"] if f"no {p}" in ratios]
    off = {p: ratios[f"no {p}"] for p in passes}
    off_c = {p: compiles.get(f"no {p}", {}) for p in passes}
    off_t = {p: traces.get(f"no {p}", {}) for p in passes}
    cheap_set = {
        p for p in passes if max([*off[p].values(), *off_c[p].values(), *off_t[p].values()]) < 1.1
    }
    cheap = ", ".join(f"`{p}`" for p in passes if p in cheap_set) or "none"
    costly = ", ".join(f"`{p}`" for p in passes if min(off[p].values()) < 1 / 1.1)
    text += (
        " A pass that buys less than 10 % on every workload, in run time, compile time and "
        "tracing (each ratio in its row below 1.10x, the run time of a program it leaves "
        "unchanged counted as 1.00x, and a compile or tracing time only where every round "
        "with the pass off took longer than every round with all passes, over at least two "
        "compilations each), is a candidate for "
        f"removal on this machine: {cheap}."
    )
    if passes:  # the workload where each pass buys the most
        most = [(p, max(off[p], key=off[p].get)) for p in passes]
        said = "; ".join(f"`{p}` {x(off[p][w])} ({d['workloads'][w]['label']})" for p, w in most)
        text += f" Each pass's largest slowdown when off: {said}."
        for kind, by_pass in (("compile time", off_c), ("tracing", off_t)):
            # (gains apart from the rounds' noise only)
            most = [(p, max(by_pass[p], key=by_pass[p].get)) for p in passes if by_pass[p]]
            said = "; ".join(
                f"`{p}` {x(by_pass[p][w])} ({d['workloads'][w]['label']})"
                for p, w in most
                if by_pass[p][w] > 1.0
            )
            text += f" Slower to compile with a pass off ({kind}): {said or 'none'}."
    if costly:
        text += f" Turned off, these make a workload over 10 % faster (below 0.91x): {costly}."
    for fwd, grad, what in (
        ("run", "run grad", "One run's gradient"),
        ("quadrotor", "quadrotor grad", "The quadrotor's value and gradient"),
    ):
        pairs = [(c, by.get((c, grad)), by.get((c, fwd))) for c in (base, "none")]
        pairs = [(c, g, f) for c, g, f in pairs if g is not None and f is not None]
        if pairs:
            said = ", ".join(f"{x(g['run_s'] / f['run_s'])} with {c}" for c, g, f in pairs)
            text += f" {what} over its forward pass: {said}."
    apart = [d["workloads"][w]["label"] for w in d.get("merged", {}) if w in d["workloads"]]
    if apart:  # (`ablation.py --merge`: every ratio is within one workload's run)
        text += f" Measured in a run of their own, on the same machine: {', '.join(apart)}."
    if "autodiff" in ratios:  # the engine's derivative strategies, apart from its passes
        said = ", ".join(
            f"{x(v)} ({d['workloads'][w]['label']})" for w, v in ratios["autodiff"].items()
        )
        text += f" Differentiated by JAX alone (autodiff) over all passes: {said}."
    lines += ["", f"{text} {sources([name])}"]
    return lines, cheap_set


@block("ablation")
def ablation(R: Results) -> str:
    names = [n for n in ["ablation.json", *R.gpu("ablation")] if R.get(n) is not None]
    if not names:
        return not_measured("ablation.py") + "\n"
    lines, cheap, machines = [], None, []
    for n in names:
        d = R.get(n)
        part, cheap_here = _ablation(d, n)
        if lines:
            lines += ["", f"On {device(d)} (JAX {env(d).get('jax', '?')}):", ""]
        lines += part
        machines.append(device(d))
        cheap = cheap_here if cheap is None else cheap & cheap_here
    if len(names) > 1:
        said = ", ".join(f"`{p}`" for p in sorted(cheap)) or "none"
        lines += [
            "",
            f"A pass is removed when it buys less than 10 % on every workload of every machine "
            f"measured ({'; '.join(machines)}): {said}.",
        ]
    return "\n".join(lines) + "\n"


@block("vehicle")
def vehicle(R: Results) -> str:
    names = R.family("vehicle")
    if not names:
        return not_measured("vehicle.py") + "\n"
    base = "plain"
    columns = [(n, dt) for n in names for dt in R.get(n)["dtypes"]]
    by = {(n, r["dtype"], r["config"]): r for n in names for r in R.get(n)["rows"]}
    configs = list(dict.fromkeys(c for n in names for c in R.get(n)["configs"]))

    def cell(name, dtype, config):
        r, b = by.get((name, dtype, config)), by.get((name, dtype, base))
        if r is None or b is None:
            return NOT_MEASURED
        if config == base:
            return (
                f"{rate(r['body_steps_per_s'])} body-steps/s, {r['layout']} program, "
                f"compile {dur(r['compile_s'])}"
            )
        lo, hi = (x(v) for v in r["ratio_range"])
        text = f"**{x(r['ratio'])}**" + ("" if lo == hi else f" ({lo[:-1]}–{hi})")
        text += f", compile {x(r['compile_ratio'])}"
        if r["same_program_as_plain"]:
            text += ", same program"
        elif r["layout"] != b["layout"]:
            text += f", {r['layout']} program"
        return text

    head = [f"{device(R.get(n))}, {dt}" for n, dt in columns]
    rows = [[c, *(cell(n, dt, c) for n, dt in columns)] for c in configs]
    lines = table(["configuration", *head], rows)
    d = R.get(names[0])
    target = d["target"]
    text = (
        f"{d['batch']} hover runs of the paper's vehicle from random attitudes, "
        f"{d['n_steps']} steps of {num(d['dt'])} s, {d['method']}, control sampled every "
        "step (`vehicle.py` lists each configuration's models). First row: the plain "
        "quadrotor's body-steps/s, the layout of its batch and its compile time; other rows: "
        "the fastest call over the plain quadrotor's in the same dtype, in brackets the "
        "middle half of that ratio over the rounds (at least "
        f"{min(len(r['rounds']) for n in names for r in R.get(n)['rows'])}, every "
        "configuration of both dtypes alternated in each), and the compile time over the "
        "plain one's. *Same program*: XLA compiled the plain quadrotor's very program (the "
        "difference is noise)."
    )
    aim = d.get("target_config", "full vehicle")
    verdicts = []
    for n, dt in columns:
        r, full = by.get((n, dt, aim)), by.get((n, dt, "full vehicle"))
        if r is not None:
            met = "met" if r["ratio"] <= target else "not met"
            said = f"{device(R.get(n))}, {dt}: {x(r['ratio'])}, {met}"
            if full is not None and aim != "full vehicle":
                said += f" (the full vehicle: {x(full['ratio'])})"
            verdicts.append(said)
    if verdicts:
        text += f" Target: *{aim}* at most {x(target)} the plain quadrotor; "
        text += "; ".join(verdicts) + "."
    why: dict[str, list[str]] = {}  # the engine's reason -> the configurations it moved
    for n in names:
        for r in R.get(n)["rows"]:
            if r.get("layout_why") and r["layout"] != by[(n, r["dtype"], base)]["layout"]:
                why.setdefault(r["layout_why"], []).append(r["config"])
    if why:
        said = "; ".join(f"{', '.join(dict.fromkeys(cs))}: {w}" for w, cs in sorted(why.items()))
        text += f" Where a model moves the batch to another program, the engine says why ({said})."
    lines += ["", f"{text} {sources(names)}"]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------
# Rewriting the Markdown files


def render(text: str, results: Results, path: str) -> tuple[str, list[str]]:
    """``text`` with every known block regenerated, and the names of blocks that changed.

    Raises `ValueError` for an unknown block name or a marker without its partner.
    """
    opened = [m.group(2) for m in OPEN.finditer(text) if not m.group(1)]
    closed = [m.group(2) for m in OPEN.finditer(text) if m.group(1)]
    paired = [m.group("name") for m in BLOCK.finditer(text)]
    if sorted(opened) != sorted(paired) or sorted(closed) != sorted(paired):
        raise ValueError(
            f"{path}: a report marker has no partner (opened {opened}, closed {closed})"
        )
    unknown = [n for n in paired if n not in BLOCKS]
    if unknown:
        raise ValueError(f"{path}: unknown report blocks {unknown}; known: {sorted(BLOCKS)}")
    stale = []
    cache: dict[str, str] = {}

    def sub(m):
        name = m.group("name")
        if name not in cache:
            cache[name] = BLOCKS[name](results)
        new = f"<!-- report:{name} -->\n{cache[name]}<!-- /report:{name} -->"
        if new != m.group(0):
            stale.append(name)
        return new

    return BLOCK.sub(sub, text), stale


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--check", action="store_true", help="write nothing; exit 1 if stale")
    p.add_argument("--root", type=Path, default=ROOT, help="the repository's root folder")
    args = p.parse_args(argv)
    results = Results(args.root / RESULTS)
    stale_any = False
    for rel in FILES:
        path = args.root / rel
        if not path.is_file():
            continue
        old = path.read_text()
        try:
            new, stale = render(old, results, rel)
        except ValueError as e:
            print(f"report.py: {e}", file=sys.stderr)
            return 2
        if not stale:
            continue
        stale_any = True
        if args.check:
            print(f"{rel}: stale report blocks: {', '.join(stale)}")
            diff = difflib.unified_diff(
                old.splitlines(keepends=True),
                new.splitlines(keepends=True),
                f"{rel} (as written)",
                f"{rel} (from {RESULTS})",
            )
            sys.stdout.writelines(diff)
        else:
            path.write_text(new)
            print(f"wrote {rel}: {', '.join(stale)}")
    if args.check and stale_any:
        print("run `python benchmarks/report.py` to regenerate them")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
