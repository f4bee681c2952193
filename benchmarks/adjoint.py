"""The discrete adjoint's two memories: every step's residuals against checkpointed segments.

`so3jax._engine.derivatives.CheckpointedAdjoint` (reverse mode through more than
``forward_jacobian_max`` scalars) keeps every step's residuals from the run's forward
pass while they take at most the policy's ``adjoint_residual_bytes`` per run, and
otherwise checkpoints segments of about ``sqrt(n_steps)`` steps and replays each. This
measures both on DiffTune's quadrotor (`difftune.py`: RKMK4, control held over each
0.0025 s step, the sum of |e_x|^2 over the run, ``value_and_grad`` through the 12 gains),
for one run and for ``jax.vmap`` over a batch of gains, each in a fresh interpreter (JAX's
traces are not shared between them): the first call (tracing and compiling included)
and the fastest later call. Configurations alternate over rounds; each figure is the
fastest, with the range. Writes ``results/adjoint[-quick].json``.

    python benchmarks/adjoint.py            # 4000 steps, a batch of 4, 3 rounds
    python benchmarks/adjoint.py --quick    # 400 steps, 1 round
"""

from __future__ import annotations

import json
import subprocess
import sys

import _common as C

#: One measurement in a fresh interpreter: prints a JSON object.
ONE = """
import json, sys, time
import jax, jax.numpy as jnp, equinox as eqx
jax.config.update("jax_enable_x64", True)
import so3jax as so3
from so3jax._engine import policy
n_steps, runs, budget = {n_steps}, {runs}, {budget}
scene = so3.scenes.quadrotor_circle(control_period=0.0025)
def loss(g):
    sc = eqx.tree_at(lambda s: s.gains, scene, g)
    return jnp.sum(so3.simulate(sc, so3.RKMK4(), 0.0025, n_steps).extras["e_x"] ** 2)
fn, gains = jax.value_and_grad(loss), scene.gains
if runs:
    fn = jax.vmap(fn)
    scale = 1 + 0.01 * jnp.arange(runs)
    gains = jax.tree.map(lambda g: g * scale.reshape((-1,) + (1,) * g.ndim), gains)
with policy.using(adjoint_residual_bytes=budget):
    plan = so3.explain(fn, gains)
    f = jax.jit(fn)
    t = time.perf_counter()
    jax.block_until_ready(f(gains))
    first = time.perf_counter() - t
runs_s = []
for _ in range({repeats}):
    t = time.perf_counter()
    value, grad = jax.block_until_ready(f(gains))
    runs_s.append(time.perf_counter() - t)
saved = [e["saved"] for e in plan.entries if e["kind"] == "adjoint"]
print(json.dumps({{"first_s": first, "run_s": min(runs_s), "saved": saved,
                  "grad_k_x": jnp.ravel(grad.k_x)[:3].tolist()}}))
"""

CONFIGS = {"residuals": 2**62, "checkpoints": 0}


def measure(n_steps: int, runs: int, budget: int, repeats: int) -> dict:
    code = ONE.format(n_steps=n_steps, runs=runs, budget=budget, repeats=repeats)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    args = C.parse_args(__doc__.splitlines()[0])
    n_steps, rounds, batch = (400, 1, 2) if args.quick else (4000, 3, 4)
    rows = []
    for what, runs in (("one run", 0), (f"vmap of {batch} runs", batch)):
        per = {name: [] for name in CONFIGS}
        for r in range(rounds):
            order = list(CONFIGS) if r % 2 == 0 else list(reversed(CONFIGS))
            for name in order:
                per[name].append(measure(n_steps, runs, CONFIGS[name], args.repeats))
        for name, ms in per.items():
            assert all(m["saved"] == [name] for m in ms), (name, ms)
            rows.append(
                {
                    "workload": what,
                    "runs": max(runs, 1),
                    "saved": name,
                    "first_s": min(m["first_s"] for m in ms),
                    "first_s_rounds": [m["first_s"] for m in ms],
                    "run_s": min(m["run_s"] for m in ms),
                    "run_s_rounds": [m["run_s"] for m in ms],
                    "grad_k_x": ms[0]["grad_k_x"],
                }
            )
    C.print_table(
        [
            {
                "workload": r["workload"],
                "saved": r["saved"],
                "first call s": r["first_s"],
                "run ms": r["run_s"] * 1e3,
            }
            for r in rows
        ],
        ["workload", "saved", "first call s", "run ms"],
        title=f"value_and_grad through 12 gains, {n_steps} steps",
    )
    json_path, _ = C.output_paths(args, "adjoint")
    C.write_json(
        json_path,
        {"env": C.environment(), "n_steps": n_steps, "rounds": rounds, "rows": rows},
    )


if __name__ == "__main__":
    main()
