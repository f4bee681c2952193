"""Work against precision: every method, on the seed scenario and the free body.

For each method, the final attitude error (geodesic distance of the final
attitude, projected onto SO(3), to a tight reference) and the final |Omega|
error, against (a) wall time per trajectory after compilation (min over
repeats), (b) vector-field evaluations and (c) compile time. Lie-group methods
run over a range of step sizes; diffrax (ambient R^9 x R^3) over a range of
tolerances (rtol = atol) and, fixed-step, classic RK4; SciPy `solve_ivp` RK45
and DOP853 over tolerances, with a plain NumPy vector field.

From the same run: each method's wall time at final attitude error 1e-8
(log-log interpolation of its curve) and its ratio to diffrax Tsit5 and SciPy
RK45 there.

Writes ``results/work_precision[-quick].json`` and ``.png``.

    python benchmarks/work_precision.py            # full (several minutes)
    python benchmarks/work_precision.py --quick    # seconds
"""

from __future__ import annotations

import math

import _common as C
import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

import so3jax as s

TARGET = 1e-8

#: Lie-group methods and their step counts over the horizon (full run).
LIE = {
    "LieEuler": (s.LieEuler, [1000, 4000, 16000, 64000]),
    "LGVI": (s.LGVI, [500, 1000, 2000, 4000, 8000, 16000, 32000]),
    "CG3": (s.CG3, [250, 500, 1000, 2000, 4000, 8000, 16000]),
    "RKMK32": (s.RKMK32, [250, 500, 1000, 2000, 4000, 8000, 16000]),
    "RKMK4": (s.RKMK4, [125, 250, 500, 1000, 2000, 4000, 8000]),
    "CF4": (s.CF4, [125, 250, 500, 1000, 2000, 4000, 8000]),
    "RKMK45": (s.RKMK45, [125, 250, 500, 1000, 2000, 4000]),
    "RKMK4 Cayley": (lambda: s.RKMK4(coords="cayley"), [125, 250, 500, 1000, 2000, 4000, 8000]),
    "RKMKTsit5 Cayley": (lambda: s.RKMKTsit5(coords="cayley"), [125, 250, 500, 1000, 2000, 4000]),
}
AMBIENT_FIXED = {"diffrax RK4": ("rk4", [125, 250, 500, 1000, 2000, 4000, 8000])}
AMBIENT_ADAPTIVE = {
    "diffrax Tsit5": "tsit5",
    "diffrax Dopri5": "dopri5",
    "diffrax Dopri8": "dopri8",
}
TOLS = [1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12, 1e-13]
SCIPY = {"SciPy RK45": "RK45", "SciPy DOP853": "DOP853"}
SCIPY_TOLS = [1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12]

QUICK_LIE = {"RKMK4": (s.RKMK4, [50, 100])}
QUICK_AMBIENT_FIXED = {"diffrax RK4": ("rk4", [100])}
QUICK_ADAPTIVE = {"diffrax Tsit5": "tsit5"}
QUICK_TOLS = [1e-6, 1e-8]
QUICK_SCIPY = {"SciPy RK45": "RK45"}


# --------------------------------------------------------------------------
# Scenes and their plain NumPy vector fields (for SciPy)
# --------------------------------------------------------------------------


def _np_hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _np_vee(W):
    return np.array([W[2, 1], W[0, 2], W[1, 0]])


def numpy_field(scene):
    """``f(t, y)`` for ``y = [R (9), (Rd (9)), Omega (3)]``: the scene written in NumPy.

    Free body: ``R' = R hat(Omega)``, ``J Omega' = -Omega x J Omega``. Seed
    (geometric tracking): ``Rd' = Rd hat(Omega_d)`` and the torque of Lee,
    Leok & McClamroch (CDC 2010), ``M = -k_R e_R - k_Omega e_Omega + Omega x J
    Omega - J (hat(Omega) R^T Rd Omega_d - R^T Rd dOmega_d)``.
    """
    J = np.asarray(scene.body.inertia)
    Jinv = np.linalg.inv(J)
    k = scene.y0.R.shape[0]
    if k == 1:

        def f(t, y):
            R, W = y[:9].reshape(3, 3), y[9:]
            dW = Jinv @ (-np.cross(W, J @ W))
            return np.concatenate([(R @ _np_hat(W)).ravel(), dW])

        return f
    gains = scene.controller.gains
    kR, kW = np.asarray(gains.k_R), np.asarray(gains.k_Omega)
    ref = scene.reference
    A, w, ph = (np.asarray(x) * np.ones(3) for x in (ref.amplitude, ref.frequency, ref.phase))
    w = 2 * np.pi * w

    def f(t, y):
        R, Rd, W = y[:9].reshape(3, 3), y[9:18].reshape(3, 3), y[18:]
        Wd, dWd = A * np.sin(w * t + ph), A * w * np.cos(w * t + ph)
        RtRd = R.T @ Rd
        e_R = 0.5 * _np_vee(Rd.T @ R - R.T @ Rd)
        e_W = W - RtRd @ Wd
        JW = J @ W
        M = -kR * e_R - kW * e_W + np.cross(W, JW) - J @ (_np_hat(W) @ RtRd @ Wd - RtRd @ dWd)
        dW = Jinv @ (M - np.cross(W, JW))
        return np.concatenate([(R @ _np_hat(W)).ravel(), (Rd @ _np_hat(Wd)).ravel(), dW])

    return f


def numpy_y0(scene):
    return np.concatenate([np.asarray(scene.y0.R).reshape(-1), np.asarray(scene.y0.x)])


def check_numpy_field(scene) -> float:
    """Max difference between the NumPy field and the scene's own (ambient) field."""
    from so3jax._ambient import _ambient_field

    y0 = scene.y0
    ref = _ambient_field(jnp.asarray(0.3), y0, scene)
    mine = numpy_field(scene)(0.3, numpy_y0(scene))
    want = np.concatenate([np.asarray(ref.R).reshape(-1), np.asarray(ref.x)])
    return float(np.max(np.abs(mine - want)))


def make_scenes(quick: bool):
    free = s.scenes.free_body(
        jnp.array([1.0, 2.0, 3.0]), s.exp(jnp.array([0.3, 0.2, -0.1])), jnp.array([0.5, 1.0, -0.3])
    )
    out = {}
    if hasattr(s.scenes, "seed"):
        out["seed"] = (s.scenes.seed(), 1.0 if quick else 10.0)
    if not quick or not out:
        out["free_body"] = (free, 1.0 if quick else 10.0)
    return out


# --------------------------------------------------------------------------
# Errors and evaluation counts
# --------------------------------------------------------------------------


def errors(R, W, R_ref, W_ref) -> dict:
    R = jnp.asarray(R)
    Rp = s.project(R) if bool(jnp.all(jnp.isfinite(R))) else R * jnp.nan
    return {
        "att_err": float(s.geodesic_distance(Rp, R_ref)),
        "omega_err": float(jnp.linalg.norm(jnp.asarray(W) - W_ref)),
        "orth_err": float(s.orthogonality_error(R)),
    }


def lie_fevals_per_step(method, scene) -> int:
    """Vector-field (or torque) evaluations per step, from the method's tableau."""
    tab = getattr(method, "tableau", None)
    if isinstance(tab, s.ButcherTableau):
        return tab.stages - (1 if tab.b[-1] == 0 else 0)  # an unused last stage is dropped
    if isinstance(tab, s.CFTableau):
        return len(tab.c)
    if isinstance(method, s.LGVI):  # torques at both ends (+ fixed-point iterations)
        return 1 if scene.torque(0.0, scene.y0) is None else 1 + method.torque_iters
    return -1


# --------------------------------------------------------------------------
# Runs
# --------------------------------------------------------------------------


def run_scene(name, scene, T, quick, repeats):
    lie = QUICK_LIE if quick else LIE
    amb_fixed = QUICK_AMBIENT_FIXED if quick else AMBIENT_FIXED
    adaptive = QUICK_ADAPTIVE if quick else AMBIENT_ADAPTIVE
    tols = QUICK_TOLS if quick else TOLS
    scipy_methods = QUICK_SCIPY if quick else SCIPY
    scipy_tols = QUICK_TOLS if quick else SCIPY_TOLS

    # Tight reference: RKMK45 (order 5, on the group), checked against Dopri8 at 1e-13.
    n_ref = 1000 if quick else 40000
    ref = s.simulate(scene, s.RKMK45(), T / n_ref, n_ref, save_every=n_ref)
    R_ref, W_ref = ref.R[-1], ref.Omega[-1]
    ref_check = None
    if not quick:
        chk = s.simulate_ambient(scene, "dopri8", T, rtol=1e-13, atol=1e-13, n_save=2)
        ref_check = errors(chk.R[-1], chk.Omega[-1], R_ref, W_ref)
    field_check = check_numpy_field(scene)
    assert field_check < 1e-10, f"NumPy field differs from the scene's by {field_check}"

    points = []
    jobs = [(k, "lie", m, ns) for k, (m, ns) in lie.items()]
    jobs += [(k, "fixed", sv, ns) for k, (sv, ns) in amb_fixed.items()]
    total = sum(len(j[3]) for j in jobs) + len(adaptive) * len(tols)
    total += len(scipy_methods) * len(scipy_tols)
    bar = C.progress(range(total), f"{name}", total=total)
    it = iter(bar)

    for label, kind, m, ns in jobs:
        for n in ns:
            next(it, None)
            dt = T / n
            if kind == "lie":
                method = m()

                def fn(sc, method=method, dt=dt, n=n):
                    tr = s.simulate(sc, method, dt, n, save_every=n)
                    return tr.R[-1], tr.Omega[-1], tr.status.code

                fev = lie_fevals_per_step(method, scene) * n
            else:

                def fn(sc, sv=m, dt=dt, n=n):
                    tr = s.simulate_ambient(sc, sv, dt=dt, n_steps=n, save_every=n)
                    return tr.R[-1], tr.Omega[-1], tr.status.code, tr.extras["num_fevals"]

            r = C.compile_and_time(fn, scene, repeats=repeats)
            out = r["out"]
            if kind != "lie":
                fev = int(out[3])
            points.append(
                {
                    "method": label,
                    "family": "lie" if kind == "lie" else "diffrax",
                    "param": "n_steps",
                    "value": n,
                    "dt": dt,
                    "run_s": r["run_s"],
                    "compile_s": r["compile_s"],
                    "fevals": fev,
                    "ok": int(out[2]) == 0,
                    **errors(out[0], out[1], R_ref, W_ref),
                }
            )

    for label, sv in adaptive.items():

        def fn(sc, tol, sv=sv):
            tr = s.simulate_ambient(sc, sv, T, rtol=tol, atol=tol, n_save=2, max_steps=50000)
            return tr.R[-1], tr.Omega[-1], tr.status.code, tr.extras["num_fevals"]

        compiled, compile_s, _ = C.compile_fn(fn, scene, jnp.asarray(tols[0]))
        for tol in tols:
            next(it, None)
            run_s, out = C.time_call(compiled, scene, jnp.asarray(tol), repeats=repeats)
            points.append(
                {
                    "method": label,
                    "family": "diffrax",
                    "param": "tol",
                    "value": tol,
                    "run_s": run_s,
                    "compile_s": compile_s,
                    "fevals": int(out[3]),
                    "ok": int(out[2]) == 0,
                    **errors(out[0], out[1], R_ref, W_ref),
                }
            )

    f = numpy_field(scene)
    y0 = numpy_y0(scene)
    k = scene.y0.R.shape[0]
    for label, sm in scipy_methods.items():
        for tol in scipy_tols:
            next(it, None)
            reps = max(1, min(repeats, 3))
            run_s, sol = C.time_python(
                lambda sm=sm, tol=tol: solve_ivp(f, (0.0, T), y0, method=sm, rtol=tol, atol=tol),
                reps,
            )
            yT = sol.y[:, -1]
            points.append(
                {
                    "method": label,
                    "family": "scipy",
                    "param": "tol",
                    "value": tol,
                    "run_s": run_s,
                    "compile_s": 0.0,
                    "fevals": int(sol.nfev),
                    "ok": bool(sol.success),
                    **errors(yT[:9].reshape(3, 3), yT[9 * k :][:3], R_ref, W_ref),
                }
            )
    bar.close()
    return {
        "T": T,
        "reference": f"RKMK45, {n_ref} steps",
        "reference_vs_dopri8_1e-13": ref_check,
        "numpy_field_max_diff": field_check,
        "points": points,
    }


def at_target(points, target=TARGET) -> dict:
    """Per method: wall time, evaluations and compile time at final attitude error `target`."""
    out = {}
    for m in dict.fromkeys(p["method"] for p in points):
        pts = [p for p in points if p["method"] == m and p["ok"]]
        err = [p["att_err"] for p in pts]
        out[m] = {
            "run_s": C.interp_loglog(err, [p["run_s"] for p in pts], target),
            "fevals": C.interp_loglog(err, [p["fevals"] for p in pts], target),
            "compile_s": float(np.median([p["compile_s"] for p in pts])) if pts else math.nan,
        }
    for base, key in (("diffrax Tsit5", "vs_tsit5"), ("SciPy RK45", "vs_rk45")):
        b = out.get(base, {}).get("run_s", math.nan)
        for v in out.values():
            v[key] = b / v["run_s"] if v["run_s"] > 0 else math.nan  # > 1: faster than base
    return out


def plot(results, path):
    scenes = list(results)
    fig, axes = C.plt.subplots(len(scenes), 3, figsize=(16, 4.6 * len(scenes)), squeeze=False)
    styles = {"lie": "-o", "diffrax": "--s", "scipy": ":^"}
    for row, name in zip(axes, scenes, strict=True):
        pts = results[name]["points"]
        methods = list(dict.fromkeys(p["method"] for p in pts))
        for m in methods:
            mp = sorted(
                (p for p in pts if p["method"] == m and p["ok"]), key=lambda p: p["att_err"]
            )
            if not mp:
                continue
            err = [max(p["att_err"], 1e-17) for p in mp]
            st = styles[mp[0]["family"]]
            row[0].loglog(err, [p["run_s"] for p in mp], st, label=m, ms=4)
            row[1].loglog(err, [p["fevals"] for p in mp], st, label=m, ms=4)
            comp = [p["compile_s"] for p in mp if p["family"] != "scipy"]
            if comp:
                row[2].loglog(err[: len(comp)], comp, st, label=m, ms=4)
        for ax, ylabel in zip(
            row,
            ["wall time per trajectory [s]", "vector-field evaluations", "compile time [s]"],
            strict=True,
        ):
            ax.axvline(TARGET, color="grey", lw=0.8)
            ax.set_xlabel("final attitude error [rad]")
            ax.set_ylabel(ylabel)
            ax.set_title(f"{name} ({results[name]['T']:g} s)")
            ax.grid(True, which="both", alpha=0.3)
        row[0].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    C.save_figure(fig, path)


def main():
    args = C.parse_args(__doc__.splitlines()[0])
    json_path, png_path = C.output_paths(args, "work_precision")
    results = {}
    for name, (scene, T) in make_scenes(args.quick).items():
        results[name] = run_scene(name, scene, T, args.quick, args.repeats)
        results[name]["at_1e-8"] = at_target(results[name]["points"])
        rows = [{"method": m, **v} for m, v in results[name]["at_1e-8"].items()]
        C.print_table(
            rows,
            ["method", "run_s", "fevals", "compile_s", "vs_tsit5", "vs_rk45"],
            f"{name}: at final attitude error {TARGET:g} (vs_*: speed-up over the baseline)",
        )
    C.write_json(json_path, {"env": C.environment(), "target": TARGET, "scenes": results})
    plot(results, png_path)


if __name__ == "__main__":
    main()
