"""Work of a compiled program's loop step, counted instead of timed.

XLA's compiled instructions (``compiled.as_text()``), each elementwise floating-point
operation weighted by the elements its fusion computes: a ``(64,)`` operation inside a
fusion whose output is ``(2, 64)`` (a Jacobian's two tangent columns over a tile of 64
runs) counts 128, since XLA computes it once per element of that output. Summed over the
operations of the run-sized shapes, it is the work of one loop step, and its ratios
(the seed gradient's over 256 runs against its forward pass's, with and without column
cuts) follow the measured times. It needs no quiet machine, so it ranks fusion choices
(the engine policy's ``column_cut_cone``, `so3jax._engine.policy.Policy`) where timings
move by 10 %.

Writes ``results/element-work[-quick].json`` and ``.png`` (each variant's step work, split
into the primal's operations, the tangent columns', and the primal's recomputed inside
the columns' fusions).

    python benchmarks/element_work.py                  # seed, RKMK4, B = 256: grad, forward
    python benchmarks/element_work.py --method CF4 --batch 64
    python benchmarks/element_work.py --quick          # LieEuler, B = 32, 20 steps
"""

from __future__ import annotations

import argparse
import collections
import re
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import _common as C  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402
import numpy as np  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import so3jax as so3  # noqa: E402
from so3jax._integrators import METHODS, method_by_name  # noqa: E402

#: Elementwise operations counted (XLA's opcode names).
OPS = frozenset(
    "multiply add subtract divide negate sine cosine sqrt rsqrt select compare maximum "
    "minimum exponential power abs".split()
)


def _elements(dims: str) -> int:
    return int(np.prod([int(d) for d in dims.split(",") if d])) if dims else 1


def element_work(hlo: str) -> dict:
    """``{(op elements, fusion output elements): weighted work}`` over the fused
    computations of compiled HLO text; the weight is the larger of the two sizes."""
    work = collections.Counter()
    current, out = None, 1
    for line in hlo.splitlines():
        head = re.match(r"^%(\S+) \(.*\) -> (.*) \{$", line)
        if head:
            current = head.group(1) if "fus" in head.group(1) else None
            shapes = re.findall(r"f(?:32|64)\[([0-9,]*)\]", head.group(2))
            out = max([_elements(s) for s in shapes] or [1])
            continue
        if line.startswith("}"):
            current = None
            continue
        op = re.search(r"= f(?:32|64)\[([0-9,]*)\]\{?[^ ]* (\w+)\(", line)
        if current and op and op.group(2) in OPS:
            e = _elements(op.group(1))
            work[(e, out)] += max(e, out)
    return dict(work)


def step_work(work: dict, sizes: set) -> int:
    """The work of the operations whose size and fusion size are both in ``sizes``."""
    return sum(w for (e, o), w in work.items() if e in sizes and o in sizes)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", default=str(Path(__file__).parent / "results"))
    p.add_argument("--method", type=method_by_name, default=None, help=", ".join(METHODS))
    p.add_argument("--batch", type=int, default=None, help="runs (default 256)")
    p.add_argument("--steps", type=int, default=None, help="steps (default 200)")
    args = p.parse_args(argv)
    args.out = Path(args.out)
    args.out.mkdir(parents=True, exist_ok=True)
    method_name = args.method or ("LieEuler" if args.quick else "RKMK4")
    B = args.batch or (32 if args.quick else 256)
    n = args.steps or (20 if args.quick else 200)
    scene, method = so3.scenes.seed(), METHODS[method_name]()
    k = jnp.array([8.81, 2.54])
    R0, W0 = so3.initial_states(jax.random.key(0), B)

    def cost(k, ck="auto"):
        return so3.expected_cost(scene, k[0], k[1], R0, W0, method, 1e-2, n, checkpoint_every=ck)

    tile = so3._engine.passes.tiles.batch_tiles("jacobian", B, 2)[1]
    rows = []
    for what, fn, sizes in (
        ("forward pass", lambda k: cost(k, None), {B}),
        ("reverse (default)", jax.grad(cost), {tile, 2 * tile}),
    ):
        work = element_work(jax.jit(fn).lower(k).compile().as_text())
        tiles = -(-B // tile) if what != "forward pass" else 1
        total = step_work(work, sizes) * tiles
        lo, hi = min(sizes), max(sizes)
        parts = {  # primal ops in primal fusions; in the columns' fusions; the columns'
            "primal": work.get((lo, lo), 0) * tiles,
            "primal in the columns' fusions": work.get((lo, hi), 0) * tiles if hi > lo else 0,
            "tangent columns": work.get((hi, hi), 0) * tiles if hi > lo else 0,
        }
        rows.append(
            {"variant": what, "batch": B, "method": method_name, "step_work": total, **parts}
        )
    base = rows[0]["step_work"]
    for r in rows:
        r["work_ratio"] = r["step_work"] / base
        print(
            f"{r['variant']:20s} {r['step_work']:10d} element operations a step "
            f"({r['work_ratio']:.2f}x)"
        )
    json_path, png_path = C.output_paths(args, "element-work")
    C.write_json(
        json_path,
        {"benchmark": "element-work", "quick": args.quick, "env": C.environment(), "rows": rows},
    )
    fig, ax = plt.subplots(figsize=(6, 2.6), constrained_layout=True)
    left = np.zeros(len(rows))
    for part in ("primal", "primal in the columns' fusions", "tangent columns"):
        vals = np.array([r[part] for r in rows], float)
        ax.barh([r["variant"] for r in rows], vals, left=left, label=part)
        left += vals
    ax.set_xlabel("element operations a loop step")
    ax.set_title(f"seed mean cost, {method_name}, {B} runs: work counted")
    ax.legend(fontsize=7)
    C.save_figure(fig, png_path)


if __name__ == "__main__":
    main()
