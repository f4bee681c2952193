"""DiffTune's quadrotor example: 100 steps of projected gradient descent on 12 gains.

The vehicle of Lee, Leok & McClamroch (m = 4.34 kg, J = diag(0.0820, 0.0845,
0.1377) kg m^2) under their geometric controller with gains k_x = 16, k_v = 5.6,
k_R = 8.81, k_Omega = 2.54 on every axis (3-vectors: 12 numbers), tracking
x_d = (2 (1 - cos t), 2 sin t, 0.1 sin t) with b1_d = e1 from rest at the origin
(Omega0 = (0, 0, 0.001)); control sampled and held over 0.0025 s for 10 s (RKMK4,
one step per hold, 4000 steps). Loss: the sum over the 4001 samples of |e_x|^2;
plain gradient descent, learning rate 1e-3, gains projected onto >= 0.5, 100
iterations (Cheng et al., "DiffTune: Auto-Tuning through Auto-Differentiation",
IEEE T-RO 2024). All through `so3jax.tune(scene, cost=..., bounds=(0.5, None),
optimizer=optax.sgd(1e-3))`.

Prints the RMSE of the position error per iteration, the tuned gains, the time of
one iteration (value and gradient, forward and reverse mode) against one forward
pass, and the wall time of the 100 iterations (compilation included and not; the
fastest of `TUNE_ROUNDS` tuning runs per mode, each compiling afresh, with the range).
JAX's traces of the run are then warm from the timings before them, so the reverse-mode
run is also timed in a fresh interpreter (`FRESH`), tracing included.
Writes ``results/difftune[-quick].json`` and ``.png``.

    python benchmarks/difftune.py            # the full example
    python benchmarks/difftune.py --quick    # 2 s horizon, 10 iterations, forward mode, untimed
"""

from __future__ import annotations

import subprocess
import sys
import time

import _common as C
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

import so3jax as so3

DT = 0.0025
LEARNING_RATE = 1e-3
LOWER_BOUND = 0.5  # on every gain
#: Tuning runs per mode (each compiles afresh): the fastest wall is reported, with the range.
TUNE_ROUNDS = 2

#: Reverse-mode tuning in a fresh interpreter: what a user's first call pays, JAX's
#: tracing included (in this process the timings above have traced the same run).
FRESH = """
import time
import jax, jax.numpy as jnp, optax
jax.config.update("jax_enable_x64", True)
import so3jax as so3
scene = so3.scenes.quadrotor_circle(control_period={dt})
cost = lambda tr: jnp.sum(tr.extras["e_x"] ** 2)
t = time.perf_counter()
so3.tune(scene, cost=cost, method=so3.RKMK4(), dt={dt}, n_steps={n_steps}, n_iter={n_iter},
         optimizer=optax.sgd({lr}), bounds=({lb}, None), gradient="reverse")
print(time.perf_counter() - t)
"""


def fresh_process_wall(n_steps: int, n_iter: int) -> float:
    """Seconds of `FRESH`'s tuning run (imports and the scene's construction excluded)."""
    code = FRESH.format(dt=DT, n_steps=n_steps, n_iter=n_iter, lr=LEARNING_RATE, lb=LOWER_BOUND)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def main():
    args = C.parse_args(__doc__.splitlines()[0])
    n_steps, n_iter = (800, 10) if args.quick else (4000, 100)
    scene = so3.scenes.quadrotor_circle(control_period=DT)
    n_samples = n_steps + 1

    def cost(tr):
        return jnp.sum(tr.extras["e_x"] ** 2)

    def loss(g):
        sc = eqx.tree_at(lambda s: s.gains, scene, g)
        return cost(so3.simulate(sc, so3.RKMK4(), DT, n_steps))

    def forward_mode(g):
        grad, value = jax.jacfwd(lambda p: (loss(p),) * 2, has_aux=True)(g)
        return value, grad

    # One forward pass and one iteration's value-and-gradient, each compiled once.
    # --quick (a smoke run) times the forward pass only: the gradients compile for 5 to
    # 10 s each, and tests/test_quadrotor.py checks them (the tuning run below still
    # compiles and runs forward mode).
    timings, grads = {}, {}
    variants = [("forward pass", loss)]
    if not args.quick:
        variants.append(("value and gradient, reverse mode", jax.value_and_grad(loss)))
        variants.append(("value and gradient, forward mode", forward_mode))
    for name, fn in variants:
        r = C.compile_and_time(fn, scene.gains, repeats=args.repeats)
        timings[name] = {"run_s": r["run_s"], "compile_s": r["compile_s"]}
        grads[name] = r["out"][1] if name.startswith("value and gradient") else None
    base = timings["forward pass"]["run_s"]
    grad_agree = None
    if not args.quick:
        g_rev, g_fwd = (
            jax.tree.leaves(grads[f"value and gradient, {m} mode"]) for m in ("reverse", "forward")
        )
        scale = max(float(jnp.max(jnp.abs(a))) for a in g_rev)
        grad_agree = (
            max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(g_fwd, g_rev, strict=True)) / scale
        )
        print(f"forward and reverse gradients agree to {grad_agree:.1e} (relative)")
    C.print_table(
        [
            {
                "what": k,
                "ms": v["run_s"] * 1e3,
                "x forward": v["run_s"] / base,
                "compile s": v["compile_s"],
            }
            for k, v in timings.items()
        ],
        ["what", "ms", "x forward", "compile s"],
        title=f"one iteration ({n_steps} steps, 12 gains)",
    )

    # The tuning run itself, in both modes (wall time including compilation).
    runs = {}

    def run_tune(mode, iterations):
        t = time.perf_counter()
        res = so3.tune(
            scene,
            cost=cost,
            method=so3.RKMK4(),
            dt=DT,
            n_steps=n_steps,
            n_iter=iterations,
            optimizer=optax.sgd(LEARNING_RATE),
            bounds=(LOWER_BOUND, None),
            gradient=mode,
        )
        return res, time.perf_counter() - t

    # --quick (a smoke run) tunes in forward mode only, once, and skips the loop-only
    # timing: each tuning run compiles its own programs, which is what takes the time.
    # Otherwise each mode tunes TUNE_ROUNDS times (each run compiles afresh; the machine
    # is shared): the fastest wall is kept and the range reported.
    for mode in ("forward",) if args.quick else ("forward", "reverse"):
        walls, walls_one = [], []
        for _ in range(1 if args.quick else TUNE_ROUNDS):
            res, wall = run_tune(mode, n_iter)
            walls.append(wall)
            # The loop alone: a run of one iteration pays the same compilations, so the
            # difference of the two walls is what n_iter - 1 compiled iterations took.
            if not args.quick:
                walls_one.append(run_tune(mode, 1)[1])
        wall = min(walls)
        loop = None
        if walls_one:
            loop = (wall - min(walls_one)) * n_iter / max(n_iter - 1, 1)
        key = f"value and gradient, {mode} mode"
        steady = n_iter * timings[key]["run_s"] if key in timings else None
        runs[mode] = {
            "result": res,
            "wall_s": wall,
            "walls_s": walls,
            "loop_s": loop,
            "steady_s": steady,
        }
        without = "" if loop is None else f"{loop:.2f} s without (scaled from {n_iter - 1}); "
        fastest = "" if steady is None else f"{n_iter} x the fastest iteration = {steady:.2f} s"
        spread = f" (runs: {', '.join(f'{w:.2f}' for w in walls)} s)" if len(walls) > 1 else ""
        print(f"{mode} mode: {n_iter} iterations in {wall:.2f} s with compilation{spread}, "
              f"{without}{fastest}")  # fmt: skip
    fresh = None
    if not args.quick:
        fresh = [fresh_process_wall(n_steps, n_iter) for _ in range(TUNE_ROUNDS)]
        runs_s = ", ".join(f"{w:.2f}" for w in fresh)
        print(f"reverse mode in a fresh process: {n_iter} iterations in {min(fresh):.2f} s "
              f"with tracing and compilation (runs: {runs_s} s)")  # fmt: skip
    agree = None
    if "reverse" in runs:
        r_f, r_r = runs["forward"]["result"], runs["reverse"]["result"]
        agree = float(np.max(np.abs(r_f.cost_history - r_r.cost_history) / r_r.cost_history))
        print(f"forward and reverse runs agree to {agree:.1e} (relative, cost history)")
    res = runs["forward"]["result"]
    rmse = np.sqrt(res.cost_history / n_samples)
    print("RMSE of |e_x| [m] by iteration:")
    print(np.array2string(rmse, precision=4, max_line_width=100))
    final = jax.tree.map(lambda a: np.asarray(a[-1]), res.gains_history)
    for name in ("k_x", "k_v", "k_R", "k_Omega"):
        print(f"  tuned {name:<8} {np.round(getattr(final, name), 3)}")
    print(f"RMSE {rmse[0]:.4f} m -> {rmse[-1]:.4f} m ({rmse[-1] / rmse[0]:.2f}x)")

    # Figure: RMSE curve, position error before and after.
    def e_x_of(g):
        sc = eqx.tree_at(lambda s: s.gains, scene, g)
        tr = so3.simulate(sc, so3.RKMK4(), DT, n_steps, save_every=4)
        return np.asarray(tr.t), np.linalg.norm(np.asarray(tr.extras["e_x"]), axis=-1)

    first = jax.tree.map(lambda a: jnp.asarray(a[0]), res.gains_history)
    last = jax.tree.map(lambda a: jnp.asarray(a[-1]), res.gains_history)
    t, e0 = e_x_of(first)
    _, e1 = e_x_of(last)
    fig, ax = C.plt.subplots(1, 2, figsize=(10, 3.6))
    ax[0].plot(rmse, "o-", ms=3)
    ax[0].set_xlabel("iteration")
    ax[0].set_ylabel("RMSE of e_x [m]")
    ax[0].set_title("DiffTune quadrotor: tuning")
    ax[0].grid(alpha=0.3)
    ax[1].plot(t, e0, label="initial gains")
    ax[1].plot(t, e1, label=f"after {n_iter} iterations")
    ax[1].set_xlabel("t [s]")
    ax[1].set_ylabel("|e_x| [m]")
    ax[1].set_title("position error")
    ax[1].legend()
    ax[1].grid(alpha=0.3)
    json_path, png_path = C.output_paths(args, "difftune")
    C.save_figure(fig, png_path)
    C.write_json(
        json_path,
        {
            "environment": C.environment(),
            "n_steps": n_steps,
            "dt": DT,
            "n_iter": n_iter,
            "learning_rate": LEARNING_RATE,
            "lower_bound": LOWER_BOUND,
            "method": "RKMK4",
            "timings": timings,
            "iteration_over_forward": {k: v["run_s"] / base for k, v in timings.items()},
            "tune_wall_s": {m: r["wall_s"] for m, r in runs.items()},
            "tune_walls_s": {m: r["walls_s"] for m, r in runs.items()},
            "tune_reverse_fresh_process_walls_s": fresh,
            "tune_loop_without_compile_s": {m: r["loop_s"] for m, r in runs.items()},
            "n_iter_times_fastest_iteration_s": {m: r["steady_s"] for m, r in runs.items()},
            "forward_reverse_agreement": agree,
            "gradient_forward_reverse_agreement": grad_agree,
            "loss_history": res.cost_history,
            "rmse_history": rmse,
            "gains_initial": {
                n: np.asarray(getattr(first, n)) for n in ("k_x", "k_v", "k_R", "k_Omega")
            },
            "gains_final": {
                n: np.asarray(getattr(final, n)) for n in ("k_x", "k_v", "k_R", "k_Omega")
            },
        },
    )


if __name__ == "__main__":
    main()
