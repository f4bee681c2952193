"""Figures of a `SweepResult` and a `TuneResult` (matplotlib).

Every function returns a `matplotlib.figure.Figure`. Scripts that only write
files should select the Agg backend first (``matplotlib.use("Agg")``).
"""

from __future__ import annotations

import numpy as np

from ._plot_log import log_floor, log_line
from ._sweep import _nan_reduce

__all__ = ["sweep_heatmaps", "settling_distribution", "worst_attitudes", "tune_figure"]

#: Legend entries of the two classes of cells without a median settling time.
UNSETTLED_LABEL = "median not settled (half or more of the runs)"
FAILED_LABEL = "every run failed (diverged or unresolved)"


def _grid_axes(result):
    if result.grid_shape is None:
        raise ValueError("heat maps need a grid sweep (grid=True)")
    return result.k_R[:: result.grid_shape[1]], result.k_Omega[: result.grid_shape[1]]


def sweep_heatmaps(result, x: str = "k_Omega", y: str = "k_R"):
    """Heat maps over two axes: settling time, failures, and the stable step.

    By default the axes are the gains, ``(k_Omega, k_R)``; either may instead be a
    parameter the sweep varied (``sweep(params=...)``: ``thrust_to_weight``,
    ``time_constant``, ``max_torque``, ...), labelled with its unit
    (`so3jax._sweep_params.PARAM_LABELS`). A parameter with one value per column is
    used as it is; a 3-vector by its entry when its three entries are equal, by its
    norm (``|...|``) otherwise. Each cell pools the runs with its two values (over
    the gains, attitudes and other parameters not on the axes; the title names
    those that vary).

    Left: median settling time. Two kinds of cells have no median time and are
    drawn as their own classes, outside the colour scale, each with a legend
    entry: cells whose median is ``inf`` (half or more of the runs with
    statistics did not settle within the horizon; this includes cells where no
    run settled) are white with hatching, and cells whose runs all failed
    (diverged or unresolved) are grey. Middle: the fraction of runs that did not
    settle for any reason (`SweepResult.not_settled_fraction`); cells marked
    ``x`` hold runs whose closed loop diverged, ``o`` runs that failed only
    numerically (resolved at a smaller step), ``?`` unresolved runs. Right, over
    the gains: the largest step known to be stable for each cell
    (`so3jax.stable_dt`), with the cells past the sweep's ``dt`` outlined: there
    the runs were re-run at smaller steps. A quadrotor sweep with no step limit
    (sampled control), or any map with a parameter axis, shows instead the median
    final position error of a quadrotor or the mean cost of an attitude scene.

    **Arguments:**

    - `result`: a `SweepResult` (of a grid sweep when both axes are gains).
    - `x`, `y`: the horizontal and vertical axes: ``"k_R"``, ``"k_Omega"`` or the
      name of a swept parameter (a key of `SweepResult.params`).

    **Returns:** a `Figure` with three panels.
    """
    if (x, y) == ("k_Omega", "k_R"):
        cells = _gain_cells(result)
    else:
        cells = _axis_cells(result, x, y)
    return _draw_heatmaps(result, cells)


def _gain_cells(result) -> dict:
    """The cells of a grid sweep over ``(k_Omega, k_R)``: one per gain pair."""
    kR, kO = _grid_axes(result)
    stable = result.as_grid(result.stable_dt)
    finite = np.isfinite(stable)
    lo = float(np.min(stable[finite])) if finite.any() else result.dt / 2
    hi = float(np.max(stable[finite])) if finite.any() else result.dt * 2
    lo, hi = min(lo, result.dt) * 0.9, max(hi, result.dt) * 1.1
    right = (stable, "largest stable dt (s), linearised", "cividis", dict(norm=_log_norm(lo, hi)))
    if not finite.any() and "final_position_error" in result.metrics:
        err = result._masked(result.metrics["final_position_error"])
        err = result.as_grid(_nan_reduce(np.nanmedian, err))
        right = (err, "median final |e_x| (m)", "cividis", {})
    marks = {
        name: result.as_grid(flag.any(axis=1))
        for name, flag in (
            ("diverged", result.diverged),
            ("numerical", result.numerical),
            ("unresolved", result.unresolved),
        )
    }
    b = result.best()
    limit = (
        f"dt <= {result.dt_stable_all:.3g} is stable for every cell"
        if finite.any()
        else "no step limit (feedback held over each step)"
    )
    return {
        "x": kO,
        "y": kR,
        "xlabel": "k_Omega",
        "ylabel": "k_R",
        "median": result.as_grid(result.median_settling_time),
        "not_settled": result.as_grid(result.not_settled_fraction),
        "right": right,
        "marks": marks,
        "beyond": result.as_grid(result.dt > result.stable_dt),
        "best": (result.k_Omega[b], result.k_R[b]),
        "per_cell": f"{result.R0.shape[0]} random attitudes per cell",
        "limit": limit,
        "pooled": _pooled(result, ("k_R", "k_Omega")),
    }


def _log_norm(lo, hi):
    from matplotlib.colors import LogNorm

    return LogNorm(lo, hi)


def _axis_values(result, name: str) -> tuple[np.ndarray, str]:
    """Per-run values `(G, N)` of a heat-map axis (a gain or a swept parameter), and its label."""
    from ._sweep_params import PARAM_LABELS

    G, N = result.cost.shape
    if name in ("k_R", "k_Omega"):
        k = np.asarray(getattr(result, name), float).reshape(G, -1)
        v, norm = _one_number(k)
        label = f"|{name}|" if norm else name
        return np.broadcast_to(v[:, None], (G, N)), label
    if name not in result.params:
        swept = ", ".join(repr(p) for p in result.params) or "none"
        raise ValueError(
            f"x and y must be 'k_R', 'k_Omega' or a parameter the sweep varied ({swept}), "
            f"got {name!r}"
        )
    v, norm = _one_number(np.asarray(result.params[name], float).reshape(N, -1))
    text, unit = PARAM_LABELS.get(name, (name, ""))
    label = (f"|{text}|" if norm else text) + (f" ({unit})" if unit else "")
    return np.broadcast_to(v[None, :], (G, N)), label


def _one_number(a: np.ndarray) -> tuple[np.ndarray, bool]:
    """Rows of ``a`` `(n, k)` as one number each: the entry if a row's entries are all
    equal in every row, else the norm (then ``True``)."""
    if np.all(a == a[:, :1]):
        return a[:, 0], False
    return np.linalg.norm(a, axis=1), True


def _axis_cells(result, x: str, y: str) -> dict:
    """The cells over two axes of which one at least is a parameter: the runs pooled by value."""
    if x == y:
        raise ValueError(f"x and y must differ, both are {x!r}")
    xv, xlabel = _axis_values(result, x)
    yv, ylabel = _axis_values(result, y)
    xs, ix = np.unique(xv, return_inverse=True)
    ys, iy = np.unique(yv, return_inverse=True)
    ix, iy = ix.reshape(xv.shape), iy.reshape(yv.shape)
    shape = (ys.size, xs.size)
    median, not_settled, right = (np.full(shape, np.nan) for _ in range(3))
    marks = {k: np.zeros(shape, bool) for k in ("diverged", "numerical", "unresolved")}
    quad = "final_position_error" in result.metrics
    value = result.metrics["final_position_error"] if quad else result.cost
    for a in range(ys.size):
        for b in range(xs.size):
            cell = (iy == a) & (ix == b)
            if not cell.any():
                continue
            kept = cell & ~result.failed
            if kept.any():
                median[a, b] = np.median(result.settling_time[kept])
                right[a, b] = (np.median if quad else np.mean)(value[kept])
            not_settled[a, b] = 1.0 - result.settled[cell].mean()
            for k in marks:
                marks[k][a, b] = getattr(result, k)[cell].any()
    title = "median final |e_x| (m)" if quad else "mean cost"
    G, N = result.cost.shape
    st = result.dt_stable_all
    if np.isfinite(st):
        limit = f"dt <= {st:.3g} is stable for every run"
    else:
        limit = "no step limit (feedback held over each step)" if st > 0 else "no known step limit"
    return {
        "x": xs,
        "y": ys,
        "xlabel": xlabel,
        "ylabel": ylabel,
        "median": median,
        "not_settled": not_settled,
        "right": (right, title, "cividis", {}),
        "marks": marks,
        "beyond": None,
        "best": None,
        "per_cell": f"{G * N} runs pooled in {ys.size} x {xs.size} cells",
        "limit": limit,
        "pooled": _pooled(result, (x, y)),
    }


def _pooled(result, axes) -> str:
    """``"; pooled over ..."``: the gains and parameters that vary but are not on the axes."""
    from ._sweep_params import PARAM_LABELS

    names = []
    for name in ("k_R", "k_Omega"):
        n = np.unique(np.asarray(getattr(result, name)), axis=0).shape[0]
        if name not in axes and n > 1:
            names.append(f"{name} ({n} values)")
    for name, col in result.params.items():
        n = np.unique(np.asarray(col).reshape(col.shape[0], -1), axis=0).shape[0]
        if name not in axes and n > 1:
            text, unit = PARAM_LABELS.get(name, (name, ""))
            names.append(f"{text}{f' ({unit})' if unit else ''}: {n} values")
    return "; pooled over " + ", ".join(names) if names else ""


def _draw_heatmaps(result, cells: dict):
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    xs, ys = cells["x"], cells["y"]
    med = cells["median"]
    horizon = result.dt * result.n_steps
    unsettled = np.isinf(med)  # its own class below, not the top of the colour scale
    med_shown = np.where(unsettled, np.nan, med)
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6), constrained_layout=True)
    panels = (
        (med_shown, "median settling time (s)", "viridis", dict(vmin=0.0, vmax=horizon)),
        (cells["not_settled"], "fraction not settled (any reason)", "magma", dict(vmin=0, vmax=1)),
        cells["right"],
    )
    for ax, (val, title, cmap, scale) in zip(axes, panels, strict=True):
        cm = plt.get_cmap(cmap).with_extremes(bad="0.75")
        m = ax.pcolormesh(_edges(xs), _edges(ys), np.ma.masked_invalid(val), cmap=cm, **scale)
        fig.colorbar(m, ax=ax)
        ax.set_xscale("log" if _is_geometric(xs) else "linear")
        ax.set_yscale("log" if _is_geometric(ys) else "linear")
        ax.set_xlabel(cells["xlabel"])
        ax.set_ylabel(cells["ylabel"])
        ax.set_title(title, fontsize=10)
    hatch = dict(facecolor="white", hatch="//", edgecolor="0.35")
    if unsettled.any():
        # pcolor (a PolyCollection) draws hatching and only the cells not masked.
        axes[0].pcolor(
            _edges(xs),
            _edges(ys),
            np.ma.masked_where(~unsettled, np.zeros(unsettled.shape)),
            cmap=ListedColormap([hatch["facecolor"]]),
            hatch=hatch["hatch"],
            edgecolor=hatch["edgecolor"],
            linewidth=0.0,
            label=UNSETTLED_LABEL,
        )
    X, Y = np.meshgrid(xs, ys)
    marks = (
        ("diverged", "x", "r", "closed loop diverged"),
        ("numerical", "o", "c", "numerical (resolved at smaller dt)"),
        ("unresolved", "$?$", "y", "unresolved"),
    )
    for name, marker, color, label in marks:
        flagged = cells["marks"][name]
        if flagged.any():
            axes[1].scatter(
                X[flagged],
                Y[flagged],
                marker=marker,
                s=28,
                # "x" and "?" are unfilled markers: they take one colour, no edge.
                **(dict(facecolors="none", edgecolors=color) if marker == "o" else dict(c=color)),
                linewidths=1.2,
                label=label,
            )
    beyond = cells["beyond"]
    if beyond is not None and beyond.any():
        axes[2].scatter(
            X[beyond],
            Y[beyond],
            marker="s",
            s=30,
            facecolors="none",
            edgecolors="r",
            label=f"dt = {result.dt:g} past the limit",
        )
        axes[2].legend(loc="lower right", fontsize=7)
    if cells["best"] is not None:
        bx, by = cells["best"]
        for ax in axes[:2]:
            ax.plot(bx, by, "w*", ms=12, mec="k", label="lowest mean cost")
    handles, labels = axes[0].get_legend_handles_labels()
    if unsettled.any():  # the legend draws a collection by its colour map: a patch shows the hatch
        handles[labels.index(UNSETTLED_LABEL)] = Patch(**hatch, label=UNSETTLED_LABEL)
    if np.isnan(med).any():
        handles.append(Patch(facecolor="0.75", label=FAILED_LABEL))
        labels.append(FAILED_LABEL)
    if handles:
        axes[0].legend(handles, labels, loc="lower right", fontsize=8)
    if axes[1].get_legend_handles_labels()[0]:
        axes[1].legend(loc="upper left", fontsize=7)
    c = result.outcome_counts()
    settle = f"Psi < {result.threshold:g}"
    if result.position_threshold is not None:
        settle += f" and |e_x| < {result.position_threshold:g} m"
    fig.suptitle(
        f"{cells['per_cell']}, horizon {horizon:g} s, {settle}, "
        f"dt = {result.dt:g}: {c['numerical']} runs numerical, {c['diverged']} diverged, "
        f"{c['unresolved']} unresolved; {cells['limit']}{cells['pooled']}",
        fontsize=10,
    )
    return fig


def _is_geometric(x) -> bool:
    x = np.asarray(x, float)
    if x.size < 3 or np.any(x <= 0):
        return False
    r = x[1:] / x[:-1]
    return bool(np.allclose(r, r[0], rtol=1e-6) and not np.isclose(r[0], 1.0))


def _edges(x):
    """Cell edges around sorted centres (geometric means on a log grid)."""
    x = np.asarray(x, float)
    if x.size == 1:
        return np.array([x[0] * 0.9, x[0] * 1.1]) if x[0] > 0 else np.array([-0.5, 0.5])
    if _is_geometric(x):
        lx = np.log(x)
        mid = 0.5 * (lx[1:] + lx[:-1])
        return np.exp(np.concatenate([[2 * lx[0] - mid[0]], mid, [2 * lx[-1] - mid[-1]]]))
    mid = 0.5 * (x[1:] + x[:-1])
    return np.concatenate([[2 * x[0] - mid[0]], mid, [2 * x[-1] - mid[-1]]])


def settling_distribution(result, gains=None, bins: int = 30):
    """Histograms of the settling time for a few gain pairs (failed runs left out).

    **Arguments:**

    - `result`: a `SweepResult`.
    - `gains`: indices of the gain pairs to show (default: the lowest mean
      cost and up to three others across the sweep).
    - `bins`: histogram bins.

    **Returns:** a `Figure`; runs that never settled are counted in the legend.
    """
    import matplotlib.pyplot as plt

    G = result.k_R.shape[0]
    if gains is None:
        b = result.best()
        others = np.linspace(0, G - 1, 4).astype(int)
        gains = [b] + [int(g) for g in others if g != b][:3]
    horizon = result.dt * result.n_steps
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    edges = np.linspace(0.0, horizon, bins + 1)
    for g in gains:
        t = result.settling_time[g][~result.failed[g]]
        unsettled = int(np.sum(~np.isfinite(t)))
        label = (
            f"k_R={_fmt(result.k_R[g])}, k_Omega={_fmt(result.k_Omega[g])} "
            f"({unsettled} unsettled, {int(result.numerical[g].sum())} numerical, "
            f"{int(result.diverged[g].sum())} diverged)"
        )
        ax.hist(t[np.isfinite(t)], bins=edges, histtype="step", lw=1.6, label=label)
    ax.set_xlabel("settling time (s)")
    ax.set_ylabel("runs")
    ax.set_title(f"settling time (Psi < {result.threshold:g}) over random initial attitudes")
    ax.legend(fontsize=7)
    return fig


def _fmt(k) -> str:
    k = np.asarray(k)
    return f"{float(k):.3g}" if k.ndim == 0 else "(" + ", ".join(f"{v:.3g}" for v in k) + ")"


def worst_attitudes(result, g: int | None = None, n_worst: int = 5):
    """Where the slow initial attitudes are: error axis on the sphere, and time against angle.

    Left: the rotation axis of ``R0`` (the initial error when ``Rd0 = I``, as
    in the seed) in a longitude–latitude map, colored by settling time.
    Right: settling time against the initial error angle, with the `n_worst`
    slowest runs circled; near 180 degrees ``e_R`` is small and the geometric
    controller is slow (almost-global stability).

    **Arguments:**

    - `result`: a `SweepResult`.
    - `g`: the gain pair (default: the lowest mean cost).
    - `n_worst`: how many slowest runs to mark.

    **Returns:** a `Figure` with two panels.
    """
    import matplotlib.pyplot as plt

    from ._so3 import to_axis_angle

    g = result.best() if g is None else int(g)
    axis, angle = (np.asarray(a) for a in to_axis_angle(result.R0))
    t = np.where(result.failed[g], np.nan, result.settling_time[g])
    horizon = result.dt * result.n_steps
    shown = np.where(np.isinf(t), horizon, t)
    lon = np.degrees(np.arctan2(axis[:, 1], axis[:, 0]))
    lat = np.degrees(np.arcsin(np.clip(axis[:, 2], -1, 1)))
    worst = result.worst_attitudes(g, n_worst)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    sc = axes[0].scatter(lon, lat, c=shown, cmap="viridis", vmin=0, vmax=horizon, s=18)
    axes[0].scatter(lon[worst], lat[worst], s=90, facecolors="none", edgecolors="r")
    fig.colorbar(sc, ax=axes[0], label="settling time (s)")
    axes[0].set_xlabel("axis longitude (deg)")
    axes[0].set_ylabel("axis latitude (deg)")
    axes[0].set_xlim(-180, 180)
    axes[0].set_ylim(-90, 90)
    axes[0].set_title("axis of the initial attitude R0", fontsize=10)
    axes[1].scatter(np.degrees(angle), shown, s=14, c="tab:blue")
    axes[1].scatter(
        np.degrees(angle[worst]),
        shown[worst],
        s=90,
        facecolors="none",
        edgecolors="r",
        label=f"{n_worst} slowest",
    )
    axes[1].axhline(horizon, color="0.5", ls=":", lw=1, label="not settled")
    axes[1].set_xlabel("initial rotation angle of R0 (deg)")
    axes[1].set_ylabel("settling time (s)")
    axes[1].legend(fontsize=8)
    fig.suptitle(f"k_R = {_fmt(result.k_R[g])}, k_Omega = {_fmt(result.k_Omega[g])}", fontsize=10)
    return fig


def tune_figure(result, before=None, after=None):
    """Cost against iteration (and the gains), plus ``Psi(t)`` before and after tuning.

    **Arguments:**

    - `result`: a `TuneResult`.
    - `before`, `after`: optional `Trajectory` of the initial and tuned gains
      (tracking scenes); when given, a third panel shows ``Psi(t)`` of both.

    **Returns:** a `Figure`.
    """
    import matplotlib.pyplot as plt

    n = 3 if before is not None or after is not None else 2
    fig, axes = plt.subplots(1, n, figsize=(4.6 * n, 3.8), constrained_layout=True)
    it = np.arange(result.cost_history.shape[0])
    axes[0].plot(it, result.cost_history, "k-")
    axes[0].plot(result.best_iteration, result.cost, "r*", ms=10, label="best")
    axes[0].set_xlabel("iteration")
    axes[0].set_ylabel("cost")
    axes[0].set_title("tracking cost", fontsize=10)
    axes[0].legend(fontsize=8)
    kR, kO = result.k_R_history, result.k_Omega_history
    axes[1].plot(it, kR.reshape(len(it), -1), "-", color="tab:blue")
    axes[1].plot(it, kO.reshape(len(it), -1), "-", color="tab:orange")
    axes[1].plot([], [], "-", color="tab:blue", label="k_R")
    axes[1].plot([], [], "-", color="tab:orange", label="k_Omega")
    axes[1].set_yscale("log")
    axes[1].set_xlabel("iteration")
    axes[1].set_title("gains", fontsize=10)
    axes[1].legend(fontsize=8)
    if n == 3:
        for traj, label in ((before, "before"), (after, "after")):
            if traj is None:
                continue
            R, Rd = np.asarray(traj.R), np.asarray(traj.Rd)
            # The trace formula: absolute round-off eps, so Psi < eps shows at the floor.
            psi = 0.5 * (3.0 - np.sum(Rd * R, axis=(-1, -2)))
            log_line(axes[2], np.asarray(traj.t), psi, floor=log_floor(R.dtype), label=label)
        axes[2].set_xlabel("t (s)")
        axes[2].set_ylabel("Psi")
        axes[2].set_title("attitude error", fontsize=10)
        axes[2].legend(fontsize=8)
    return fig
