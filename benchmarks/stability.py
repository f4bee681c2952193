"""Where methods fail: stiff gains, long horizons, large steps on the Dzhanibekov flip.

1. *Largest stable step against the gains* (seed scenario, gains ``g k_R``,
   ``g k_Omega``: the fast closed-loop mode ``~ -g k_Omega / J`` stiffens with
   ``g``). A step size is stable when the run stays finite and its final state
   is within 0.05 rad (attitude) and 0.1 rad/s (rate) of a tight reference. A
   vmapped grid of step sizes (each candidate takes its own number of steps to
   the same horizon, masked inside one scan) is refined once around the
   boundary: a vectorised bisection. Adaptive diffrax Tsit5 is shown by the
   mean step it chooses (rtol = atol = 1e-6).
2. *Long horizons* (free body, 1e6 steps of 0.01 s; ``--quick``: 1e3):
   ``||R^T R - I||``, relative energy error and relative ``|Pi|`` error over
   time for every method; the ambient (diffrax) ones drift off the group.
3. *Large steps on the Dzhanibekov scene* (spin about the intermediate axis,
   tiny perturbation): the number of flips of ``Omega_2`` over the horizon for
   each step size, against a reference; a method keeps the qualitative
   behaviour when it flips as often as the reference.

Writes ``results/stability[-quick].json`` and ``.png``.

    python benchmarks/stability.py            # full (several minutes)
    python benchmarks/stability.py --quick    # seconds
"""

from __future__ import annotations

import math
import time

import _common as C
import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import so3jax as s
from so3jax._ambient import _ambient_field

LIE = C.lie_methods()
QUICK_LIE = ("RKMK4",)


def stepper(label):
    """``step(scene, t, y, h) -> (y1, failed)`` for a Lie method or an ambient diffrax one."""
    if label in LIE:
        method = LIE[label]()
        return method.step
    project = label.endswith("projected")
    solver = s.RK4()
    term = diffrax.ODETerm(_ambient_field)

    def step(scene, t, y, h):
        st = solver.init(term, t, t + h, y, scene)
        y1, _, _, _, res = solver.step(term, t, t + h, y, scene, st, False)
        if project:
            y1 = s.LieState(s.project(y1.R), y1.x)
        return y1, res != diffrax.RESULTS.successful

    return step


def ambient_labels(quick):
    return ["diffrax RK4"] if quick else ["diffrax RK4", "diffrax RK4 projected"]


def masked_run(step, scene, dts, ns, n_max, track=None, track0=None):
    """Run each ``(dt, n)`` for ``n`` steps (masked past it), vmapped over candidates.

    ``n_max`` is a traced bound of a `jax.lax.fori_loop`, so one compilation
    serves every grid.

    **Returns:** ``(y_final, ok, tracked)``, batched over the candidates.
    """

    def one(dt, n):
        def body(k, carry):
            y, ok, tr = carry
            active = k < n
            y1, failed = step(scene, k * dt, y, dt)
            good = ~failed
            for leaf in jax.tree.leaves(y1):
                good = good & jnp.all(jnp.isfinite(leaf))
            ok = ok & (good | ~active)
            upd = active & ok
            y = jax.tree.map(lambda a, b: jnp.where(upd, a, b), y1, y)
            if track is not None:
                tr = jax.tree.map(lambda a, b: jnp.where(upd, a, b), track(tr, y1), tr)
            return y, ok, tr

        return jax.lax.fori_loop(0, n_max, body, (scene.y0, jnp.array(True), track0))

    return jax.vmap(one)(dts, ns)


# --------------------------------------------------------------------------
# 1. Largest stable dt against the gains
# --------------------------------------------------------------------------


def with_gains(scene, g):
    gains = scene.controller.gains
    return eqx.tree_at(
        lambda sc: (sc.controller.gains.k_R, sc.controller.gains.k_Omega),
        scene,
        (gains.k_R * g, gains.k_Omega * g),
    )


def stable_dt(args):
    T = 1.0 if args.quick else 5.0
    gains = [1.0, 4.0] if args.quick else [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0]
    n_grid, n_fine = (8, 6) if args.quick else (24, 12)
    labels = list(QUICK_LIE if args.quick else LIE) + ambient_labels(args.quick)
    base = s.scenes.seed()
    out = {"T": T, "gains": gains, "max_dt": {}, "tsit5_mean_dt": [], "tsit5_steps": []}

    def criterion(y, ok, R_ref, W_ref):
        att = s.geodesic_distance(y.R[:, 0], R_ref)
        dw = jnp.linalg.norm(y.x[:, :3] - W_ref, axis=-1)
        return np.asarray(ok & (att < 0.05) & (dw < 0.1))

    refs = []
    for g in gains:
        sc = with_gains(base, g)
        n_ref = int(T * max(gains) * 400)  # one compilation for all gains
        ref = s.simulate(sc, s.RKMK45(), T / n_ref, n_ref, save_every=n_ref)
        refs.append((sc, ref.R[-1], ref.Omega[-1]))
        if not args.quick:
            tr = s.simulate_ambient(sc, "tsit5", T, rtol=1e-6, atol=1e-6, n_save=2)
            n_acc = int(tr.extras["num_accepted_steps"])
            out["tsit5_steps"].append(n_acc)
            out["tsit5_mean_dt"].append(T / n_acc)

    for label in C.progress(labels, "stable dt"):
        step = stepper(label)
        run = jax.jit(lambda sc, dts, ns, n_max, step=step: masked_run(step, sc, dts, ns, n_max))
        res = []
        for g, (sc, R_ref, W_ref) in zip(gains, refs, strict=True):
            # Candidates from far below to far above the explicit limit ~ 3 / (g k_Omega / J).
            lo, hi = 0.003 / g, 1.0 / g
            dts = np.geomspace(lo, hi, n_grid)
            ns = np.maximum(1, np.round(T / dts)).astype(np.int32)
            y, ok, _ = run(sc, jnp.asarray(T / ns), jnp.asarray(ns), jnp.asarray(ns.max()))
            good = criterion(y, ok, R_ref, W_ref)
            if not good[0]:
                res.append(math.nan)
                continue
            k = int(np.argmin(good)) - 1 if not good.all() else n_grid - 1
            if k == n_grid - 1:
                res.append(float(T / ns[k]))
                continue
            fine = np.geomspace(T / ns[k], T / ns[k + 1], n_fine + 2)[1:-1]
            nf = np.maximum(1, np.round(T / fine)).astype(np.int32)
            # Padded to the coarse grid's length (repeating the last candidate): the
            # program compiled for the coarse grid runs it.
            pad = np.concatenate([nf, np.repeat(nf[-1:], n_grid - n_fine)])
            y, ok, _ = run(sc, jnp.asarray(T / pad), jnp.asarray(pad), jnp.asarray(pad.max()))
            gf = criterion(y, ok, R_ref, W_ref)[:n_fine]
            j = int(np.argmin(gf)) - 1 if not gf.all() else len(nf) - 1
            res.append(float(T / nf[j]) if j >= 0 else float(T / ns[k]))
        out["max_dt"][label] = res
    return out


# --------------------------------------------------------------------------
# 2. Long horizons on the free body
# --------------------------------------------------------------------------


def long_horizon(args):
    n_steps = 1000 if args.quick else 1_000_000
    dt = 0.01
    n_save = 50 if args.quick else 100
    every = n_steps // n_save
    sc = s.scenes.free_body(
        jnp.array([1.0, 2.0, 3.0]), s.exp(jnp.array([0.3, 0.2, -0.1])), jnp.array([0.5, 1.0, -0.3])
    )
    body = sc.body
    E0 = float(body.kinetic_energy(sc.y0.x))
    P0 = float(jnp.linalg.norm(body.body_momentum(sc.y0.x)))
    lie = list(QUICK_LIE if args.quick else LIE)
    # The same methods with Kahan-compensated rotation updates (simulate(compensated=True)).
    labels = lie + [f"{k} compensated" for k in lie] + ambient_labels(args.quick)
    if not args.quick:
        labels += ["diffrax Tsit5 1e-8"]
    out = {"dt": dt, "n_steps": n_steps, "series": {}}
    for label in C.progress(labels, "long horizon"):
        t = time.perf_counter()
        if label in LIE:
            tr = s.simulate(sc, LIE[label](), dt, n_steps, save_every=every)
        elif label.endswith(" compensated"):
            method = LIE[label.removesuffix(" compensated")]()
            tr = s.simulate(sc, method, dt, n_steps, save_every=every, compensated=True)
        elif label.startswith("diffrax RK4"):
            proj = label.endswith("projected")
            tr = s.simulate_ambient(
                sc, "rk4", dt=dt, n_steps=n_steps, save_every=every, project=proj
            )
        else:
            tr = s.simulate_ambient(
                sc,
                "tsit5",
                n_steps * dt,
                rtol=1e-8,
                atol=1e-8,
                n_save=n_save + 1,
                max_steps=4 * n_steps,
            )
        jax.block_until_ready(tr.R)
        wall = time.perf_counter() - t
        R, W = np.asarray(tr.R), np.asarray(tr.Omega)  # NaN past a blow-up
        orth = np.linalg.norm(np.swapaxes(R, -1, -2) @ R - np.eye(3), axis=(-1, -2))
        Jn = np.asarray(body.inertia)
        E = 0.5 * np.einsum("ni,ij,nj->n", W, Jn, W)
        P = np.linalg.norm(W @ Jn.T, axis=-1)
        out["series"][label] = {
            "t": np.asarray(tr.t),
            "orth_err": orth,
            "energy_err": np.abs(E - E0) / E0,
            "casimir_err": np.abs(P - P0) / P0,
            "final_orth_err": float(orth[-1]),
            "max_orth_err": float(np.nanmax(orth)),
            "final_energy_err": float(abs(E[-1] - E0) / E0),
            "final_casimir_err": float(abs(P[-1] - P0) / P0),
            "wall_s_incl_compile": wall,
            "status": int(tr.status.code),
            "steps": int(tr.extras["num_steps"]) if "num_steps" in tr.extras else n_steps,
        }
    return out


# --------------------------------------------------------------------------
# 3. Large steps on the Dzhanibekov flip
# --------------------------------------------------------------------------


def dzhanibekov_scene():
    if hasattr(s.scenes, "dzhanibekov"):
        return s.scenes.dzhanibekov()
    spin, eps = 5.0, 0.01
    return s.scenes.free_body(
        jnp.array([1.0, 2.0, 3.0]), jnp.eye(3), jnp.array([eps, 1, eps]) * spin
    )


def flips(args):
    sc = dzhanibekov_scene()
    spin = float(jnp.abs(sc.y0.x[1]))
    T = 10.0 if args.quick else 60.0
    dts = [0.01, 0.1] if args.quick else [0.005, 0.01, 0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4]
    labels = list(QUICK_LIE if args.quick else LIE) + ambient_labels(args.quick)

    def track(tr, y):  # a flip: Omega_2 crosses -sign * spin / 2 (hysteresis)
        sign, count = tr
        flip = sign * y.x[1] < -0.5 * spin
        return (jnp.where(flip, -sign, sign), count + flip.astype(jnp.int32))

    track0 = (jnp.sign(sc.y0.x[1]), jnp.array(0, jnp.int32))

    def count(step, dt_list):
        dts = np.asarray(dt_list)
        ns = np.round(T / dts).astype(np.int32)
        run = jax.jit(lambda *a: masked_run(step, sc, *a, track, track0))
        _, ok, (_, c) = run(jnp.asarray(T / ns), jnp.asarray(ns), jnp.asarray(ns.max()))
        return np.where(np.asarray(ok), np.asarray(c), -1)

    dt_ref = 1e-3
    ref = int(count(stepper("RKMK45"), [dt_ref])[0])
    out = {
        "T": T,
        "dts": dts,
        "reference_flips": ref,
        "reference": f"RKMK45, dt = {dt_ref}",
        "flips": {},
    }
    for label in C.progress(labels, "flips"):
        out["flips"][label] = count(stepper(label), dts).tolist()
    for tol in [] if args.quick else [1e-3, 1e-5, 1e-8]:
        n_save = int(T * 50) + 1
        tr = s.simulate_ambient(sc, "tsit5", T, rtol=tol, atol=tol, n_save=n_save)
        w2 = np.asarray(tr.Omega[:, 1])
        sign, c = np.sign(w2[0]), 0
        for w in w2:
            if sign * w < -0.5 * spin:
                sign, c = -sign, c + 1
        out["flips"][f"diffrax Tsit5 {tol:g}"] = {
            "flips": c,
            "mean_dt": T / int(tr.extras["num_accepted_steps"]),
        }
    return out


def plot(res, path):
    fig, axes = C.plt.subplots(2, 3, figsize=(17, 9))
    ax = axes[0, 0]
    sd = res["stable_dt"]
    for label, v in sd["max_dt"].items():
        ax.loglog(sd["gains"], v, "--s" if "diffrax" in label else "-o", label=label, ms=4)
    if sd["tsit5_mean_dt"]:
        ax.loglog(sd["gains"], sd["tsit5_mean_dt"], ":k^", label="Tsit5 mean dt (1e-6)")
    ax.set_xlabel("gain scale g (k_R, k_Omega times g)")
    ax.set_ylabel("largest stable dt [s]")
    ax.set_title(f"seed scenario, stiff gains ({sd['T']:g} s)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    lh = res["long_horizon"]
    for ax, key, title in zip(
        [axes[0, 1], axes[0, 2], axes[1, 0]],
        ["orth_err", "energy_err", "casimir_err"],
        ["||R^T R - I||", "relative energy error", "relative |Pi| error"],
        strict=True,
    ):
        for label, v in lh["series"].items():
            y = np.maximum(np.asarray(v[key], float), 1e-17)
            ax.loglog(
                np.asarray(v["t"])[1:],
                y[1:],
                "--" if "diffrax" in label else ":" if "compensated" in label else "-",
                label=label,
            )
        ax.set_xlabel("t [s]")
        ax.set_title(f"free body, dt = {lh['dt']:g}: {title}")
        ax.grid(True, which="both", alpha=0.3)
    axes[0, 1].legend(fontsize=7)
    fl = res["flips"]
    ax = axes[1, 1]
    for label, v in fl["flips"].items():
        if isinstance(v, list):
            y = np.where(np.asarray(v) < 0, np.nan, v)
            ax.semilogx(fl["dts"], y, "--s" if "diffrax" in label else "-o", label=label, ms=4)
    ax.axhline(fl["reference_flips"], color="k", lw=1, label="reference")
    ax.set_xlabel("dt [s]")
    ax.set_ylabel(f"flips of Omega_2 in {fl['T']:g} s")
    ax.set_title("Dzhanibekov: flips against step size (missing: blew up)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    axes[1, 2].axis("off")
    fig.tight_layout()
    C.save_figure(fig, path)


def main():
    def extra(p):
        p.add_argument(
            "--long-only",
            action="store_true",
            help="rerun only the long horizons; keep the other parts of the existing JSON",
        )

    args = C.parse_args(__doc__.splitlines()[0], extra)
    json_path, png_path = C.output_paths(args, "stability")
    if args.long_only:
        import json

        old = json.loads(open(json_path).read())
        res = {"stable_dt": old["stable_dt"], "long_horizon": long_horizon(args)}
        res["flips"] = old["flips"]
    else:
        res = {"stable_dt": stable_dt(args), "long_horizon": long_horizon(args)}
        res["flips"] = flips(args)
    sd = res["stable_dt"]
    C.print_table(
        [
            {"method": k, **{f"g={g:g}": v for g, v in zip(sd["gains"], vals, strict=True)}}
            for k, vals in sd["max_dt"].items()
        ]
        + [
            {
                "method": "Tsit5 mean dt",
                **{f"g={g:g}": v for g, v in zip(sd["gains"], sd["tsit5_mean_dt"], strict=False)},
            }
        ],
        ["method"] + [f"g={g:g}" for g in sd["gains"]],
        "largest stable dt [s] on the seed scenario, gains x g",
    )
    lh = res["long_horizon"]
    C.print_table(
        [{"method": k, **v} for k, v in lh["series"].items()],
        [
            "method",
            "final_orth_err",
            "max_orth_err",
            "final_energy_err",
            "final_casimir_err",
            "wall_s_incl_compile",
            "steps",
        ],
        f"free body, {lh['n_steps']} steps of {lh['dt']:g} s",
    )
    fl = res["flips"]
    rows = []
    for k, v in fl["flips"].items():
        if isinstance(v, list):
            rows.append(
                {"method": k, **{f"dt={d:g}": c for d, c in zip(fl["dts"], v, strict=True)}}
            )
    C.print_table(
        rows,
        ["method"] + [f"dt={d:g}" for d in fl["dts"]],
        f"Dzhanibekov flips in {fl['T']:g} s (reference {fl['reference_flips']}; -1: blew up)",
    )
    C.write_json(json_path, {"env": C.environment(), **res})
    plot(res, png_path)


if __name__ == "__main__":
    main()
