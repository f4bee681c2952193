"""Shared helpers of the benchmark scripts: arguments, timing, JSON, charts, tables.

Every script compiles once (timed separately), then times the compiled call
with `jax.block_until_ready` over repeats and keeps the minimum. Results go to
``<out>/<name>[-quick].json`` and ``.png``; quick runs never overwrite full ones.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import math
import os
import platform
import resource
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402, F401  (re-exported for the scripts)
import numpy as np  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def parse_args(description: str, extra=None) -> argparse.Namespace:
    """``--quick`` (seconds, small sizes), ``--out`` (results folder), ``--repeats``."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--quick", action="store_true", help="small sizes: a few seconds")
    p.add_argument("--out", type=Path, default=RESULTS, help="folder for the JSON and PNG")
    p.add_argument("--repeats", type=int, default=None, help="timing repeats (min is kept)")
    if extra is not None:
        extra(p)
    args = p.parse_args()
    if args.repeats is None:
        args.repeats = 2 if args.quick else 5
    args.out.mkdir(parents=True, exist_ok=True)
    return args


def progress(iterable, desc: str, total: int | None = None):
    """A tqdm bar on stderr (plain iteration when tqdm is missing)."""
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover
        return iterable
    return tqdm(iterable, desc=desc, total=total, leave=False, file=sys.stderr)


@contextlib.contextmanager
def engine_settings(**values):
    """Trace with the engine's policy changed (`so3jax._engine.policy.using`), restored on
    exit.

    ``values`` are fields of `so3jax._engine.policy.Policy`; a table (``batched_layout``,
    ``gpu_layout``) given as a dict is merged into the active one. JAX's caches are
    cleared on entry and exit: JAX caches the batched jaxpr of every jitted function
    inside `simulate`, so without clearing, a trace after the first could reuse the first
    one's choices.
    """
    from so3jax._engine import policy

    active = policy.current()
    for table in ("batched_layout", "gpu_layout"):
        if isinstance(values.get(table), dict):
            values[table] = {**dict(getattr(active, table)), **values[table]}
    jax.clear_caches()
    try:
        with policy.using(**values):
            yield
    finally:
        jax.clear_caches()


def compile_fn(fn, *args) -> tuple[object, float, int | None]:
    """Lower and compile ``jax.jit(fn)`` for ``args``.

    **Returns:** ``(compiled, compile_s, memory_bytes)``; ``memory_bytes`` is
    arguments + outputs + temporaries from XLA's memory analysis (None if the
    backend does not say).
    """
    t = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t
    mem = None
    try:
        m = compiled.memory_analysis()
        mem = int(m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes)
    except Exception:  # pragma: no cover - backend without memory analysis
        pass
    return compiled, compile_s, mem


def time_call(compiled, *args, repeats: int = 5) -> tuple[float, object]:
    """Min wall time of ``compiled(*args)`` over ``repeats`` (after one warm-up call)."""
    out = jax.block_until_ready(compiled(*args))
    best = math.inf
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        out = jax.block_until_ready(compiled(*args))
        best = min(best, time.perf_counter() - t)
    return best, out


def compile_and_time(fn, *args, repeats: int = 5) -> dict:
    """`compile_fn` then `time_call`: ``compile_s``, ``run_s``, ``memory_bytes``, ``out``."""
    compiled, compile_s, mem = compile_fn(fn, *args)
    run_s, out = time_call(compiled, *args, repeats=repeats)
    return {"compile_s": compile_s, "run_s": run_s, "memory_bytes": mem, "out": out}


def time_python(fn, repeats: int) -> tuple[float, object]:
    """Min wall time of a plain Python call (e.g. SciPy) over repeats, and its result."""
    best, out = math.inf, None
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def environment() -> dict:
    """Where the figures were measured: versions, backend, device kind, cores."""
    dev = jax.devices()[0]
    return {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "device_kind": getattr(dev, "device_kind", str(dev)),
        "device_count": jax.device_count(),
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "x64": bool(jax.config.jax_enable_x64),
        "peak_rss_mb": peak_rss_mb(),
        "allocator": allocator(),
    }


def allocator() -> dict:
    """The allocator settings in this process's environment (glibc's ``MALLOC_*`` and
    ``GLIBC_TUNABLES``, a preloaded allocator): they change the time of calls whose XLA
    buffers exceed glibc's mmap threshold (`allocator.py`)."""
    names = ("GLIBC_TUNABLES", "LD_PRELOAD")
    return {k: v for k, v in sorted(os.environ.items()) if k.startswith("MALLOC_") or k in names}


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MiB)."""
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024 if sys.platform != "darwin" else kb / 2**20


def _clean(x):
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    if isinstance(x, np.ndarray | jax.Array):
        return _clean(np.asarray(x).tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def output_paths(args, name: str) -> tuple[Path, Path]:
    """``<out>/<name>[-<backend>][-quick].{json,png}``: a GPU run writes ``name-gpu``,
    so it never overwrites the CPU figures."""
    if jax.default_backend() != "cpu":
        name = f"{name}-{jax.default_backend()}"
    stem = f"{name}-quick" if args.quick else name
    return args.out / f"{stem}.json", args.out / f"{stem}.png"


def write_json(path: Path, data: dict, quiet: bool = False) -> None:
    """JSON with NaN/inf written as null (``quiet``: no line printed)."""
    path.write_text(json.dumps(_clean(data), indent=1) + "\n")
    if not quiet:
        print(f"wrote {path}")


def write_partial(args, name: str, rows: list) -> None:
    """The rows measured so far, to ``<name>[-<backend>][-quick].partial.json``.

    Long runs (a device lease with a time limit) keep what finished when a later
    step is cut off; the complete JSON replaces nothing until the end.
    """
    path = output_paths(args, name)[0].with_suffix(".partial.json")
    write_json(path, {"env": environment(), "rows": rows}, quiet=True)


def save_figure(fig, path: Path) -> None:
    """The figure as a PNG; a quick run's (``-quick``, a smoke test) at a low resolution."""
    if path.stem.endswith("-quick"):
        fig.savefig(path, dpi=40)
    else:
        fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    print(f"wrote {path}")


def print_table(rows: list[dict], columns: list[str], title: str = "") -> None:
    """A plain text table (floats in %.3g)."""

    def fmt(v):
        if isinstance(v, float):
            return "-" if not math.isfinite(v) else f"{v:.3g}"
        return "-" if v is None else str(v)

    cells = [[fmt(r.get(c)) for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    if title:
        print(f"\n{title}")
    print("  ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True)))
    print("  ".join("-" * w for w in widths))
    for row in cells:
        print("  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)))


def interp_loglog(err, cost, target: float) -> float:
    """Cost at error ``target`` by linear interpolation in log-log (NaN outside the range).

    Points are sorted by error; non-finite or non-positive points are dropped.
    """
    err, cost = np.asarray(err, float), np.asarray(cost, float)
    ok = np.isfinite(err) & np.isfinite(cost) & (err > 0) & (cost > 0)
    err, cost = err[ok], cost[ok]
    if err.size < 2:
        return math.nan
    order = np.argsort(err)
    le, lc = np.log(err[order]), np.log(cost[order])
    lt = math.log(target)
    if lt < le[0] or lt > le[-1]:
        return math.nan
    return float(np.exp(np.interp(lt, le, lc)))


def lie_methods() -> dict:
    """The fixed-step Lie-group methods the benchmarks compare, by display name."""
    import so3jax as s

    return {
        "LieEuler": s.LieEuler,
        "CG3": s.CG3,
        "RKMK4": s.RKMK4,
        "CF4": s.CF4,
        "RKMK45": s.RKMK45,
        "LGVI": s.LGVI,
    }
