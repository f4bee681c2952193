"""Step cost of each Lie-group method on the free rigid body.

For every method: microseconds per step of one trajectory (a long run saved
only at the end), compile time of that call, and body-steps per second of a
vmapped batch. Also a structure-of-arrays micro-benchmark (the group update
``R <- R exp(w)`` written on separate component arrays) that shows how much of
the batched cost is array layout rather than arithmetic.

Writes ``results/integrators[-quick].json`` and ``.png``.

    python benchmarks/integrators.py            # full (about a minute)
    python benchmarks/integrators.py --quick    # seconds
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import _common as C  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402

import so3jax as so3  # noqa: E402
from so3jax._so3 import _exp, _mm  # noqa: E402

METHODS = C.lie_methods()
QUICK_METHODS = ("LieEuler", "RKMK4", "CF4", "LGVI")


def best_time(fn, repeats: int) -> tuple[float, float]:
    """(first call incl. compilation, min over repeats) in seconds."""
    t = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return first, min(times)


def free_body_scene(R0):
    return so3.scenes.free_body(jnp.array([1.0, 2.0, 3.0]), R0, jnp.array([0.5, 1.0, -0.3]))


@eqx.filter_jit
def _batch(R0s, method, dt, n):
    def one(R0):
        return so3.simulate(free_body_scene(R0), method, dt, n, save_every=n).R[-1]

    return jax.vmap(one)(R0s)


def soa_update(batch: int, n: int) -> float:
    """Group updates per second with components as separate (batch,) arrays."""
    w = 0.01 * jax.random.normal(jax.random.key(0), (3, batch))

    def exp_c(w0, w1, w2):
        t = w0 * w0 + w1 * w1 + w2 * w2
        th = jnp.sqrt(t)
        A = jnp.sin(th) / th
        B = 2 * (jnp.sin(0.5 * th) / th) ** 2
        c = 1 - B * t
        return (
            (c + B * w0 * w0, -A * w2 + B * w0 * w1, A * w1 + B * w0 * w2),
            (A * w2 + B * w1 * w0, c + B * w1 * w1, -A * w0 + B * w1 * w2),
            (-A * w1 + B * w2 * w0, A * w0 + B * w2 * w1, c + B * w2 * w2),
        )

    @jax.jit
    def run(w):
        eye = tuple(tuple(jnp.full((batch,), float(i == j)) for j in range(3)) for i in range(3))

        def body(_, Rt):
            E = exp_c(w[0], w[1], w[2])
            return tuple(
                tuple(sum(Rt[i][k] * E[k][j] for k in range(3)) for j in range(3)) for i in range(3)
            )

        return jax.lax.fori_loop(0, n, body, eye)

    _, t = best_time(lambda: run(w), 3)
    return batch * n / t


def aos_update(batch: int, n: int) -> float:
    """Group updates per second with the library's (batch, 3, 3) layout."""
    w = 0.01 * jax.random.normal(jax.random.key(0), (batch, 3))

    @jax.jit
    def run(w):
        R = jnp.broadcast_to(jnp.eye(3), (batch, 3, 3))
        return jax.lax.fori_loop(0, n, lambda _, R: _mm(R, _exp(w)), R)

    _, t = best_time(lambda: run(w), 3)
    return batch * n / t


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small sizes (a few seconds)")
    p.add_argument("--out", default=str(Path(__file__).parent / "results"), help="output folder")
    p.add_argument("--repeats", type=int, default=None, help="timing repeats (min is kept)")
    args = p.parse_args(argv)
    n_single = 2_000 if args.quick else 100_000
    # --quick (a smoke run): four methods, and a batch small enough for the array
    # program (64 runs would compile the scalarized one: seconds per method).
    batch, n_batch = (8, 50) if args.quick else (4096, 200)
    methods = {k: METHODS[k] for k in QUICK_METHODS} if args.quick else METHODS
    repeats = args.repeats or (2 if args.quick else 5)
    dt = 1e-3
    scene = free_body_scene(so3.exp(jnp.array([0.3, 0.2, -0.1])))
    R0s = so3.random_rotation(jax.random.key(1), (batch,))

    rows = []
    for name, cls in methods.items():
        m = cls()
        first, t = best_time(
            lambda m=m: so3.simulate(scene, m, dt, n_single, save_every=n_single).R, repeats
        )
        bfirst, bt = best_time(lambda m=m: _batch(R0s, m, dt, n_batch), repeats)
        row = {
            "method": name,
            "order": m.order,
            "us_per_step": 1e6 * t / n_single,
            "compile_s": first - t,
            "batch": batch,
            "batch_body_steps_per_s": batch * n_batch / bt,
            "batch_compile_s": bfirst - bt,
        }
        rows.append(row)
        print(
            f"{name:9s} order {m.order}  {row['us_per_step']:6.2f} us/step  "
            f"compile {row['compile_s']:5.2f} s  batch {batch}: "
            f"{row['batch_body_steps_per_s']:.3g} body-steps/s "
            f"(compile {row['batch_compile_s']:.2f} s)"
        )
    layout = {
        "aos_updates_per_s": aos_update(batch, n_batch),
        "soa_updates_per_s": soa_update(batch, n_batch),
    }
    print(
        f"R <- R exp(w), batch {batch}: (batch,3,3) layout {layout['aos_updates_per_s']:.3g}/s, "
        f"component arrays {layout['soa_updates_per_s']:.3g}/s "
        f"(x{layout['soa_updates_per_s'] / layout['aos_updates_per_s']:.1f})"
    )

    args.out = Path(args.out)
    args.out.mkdir(parents=True, exist_ok=True)
    json_path, png_path = C.output_paths(args, "integrators")
    meta = {"dtype": "float64", "dt": dt, "n_single": n_single, "n_batch_steps": n_batch}
    C.write_json(
        json_path, {"env": C.environment(), "meta": meta, "methods": rows, "layout": layout}
    )

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    names = [r["method"] for r in rows]
    axes[0].bar(names, [r["us_per_step"] for r in rows], color="tab:blue")
    axes[0].set_ylabel("microseconds per step (one trajectory)")
    axes[0].set_title("single trajectory, float64")
    axes[1].bar(names, [r["batch_body_steps_per_s"] for r in rows], color="tab:green")
    axes[1].set_yscale("log")
    axes[1].set_ylabel("body-steps per second")
    axes[1].set_title(f"vmapped batch of {batch}, float64")
    for ax in axes:
        ax.tick_params(axis="x", rotation=30)
    fig.tight_layout()
    C.save_figure(fig, png_path)


if __name__ == "__main__":
    main()
