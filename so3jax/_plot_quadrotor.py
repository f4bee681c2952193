"""Figures of a quadrotor `Trajectory` (`scenes.quadrotor`): tracking and the 3-D path.

Both take one run whose `Trajectory.extras` hold ``x``, ``x_d``, ``e_x``, ``Psi``,
``f`` (what `scenes.quadrotor` saves). ``e3`` points down, so the plots show
the altitude ``-x_3`` ("up").
"""

from __future__ import annotations

import numpy as np

from ._plot_log import log_floor, log_line

_AXIS_COLORS = ("tab:red", "tab:green", "tab:blue")


def _extras(traj, *names):
    missing = [n for n in names if n not in traj.extras]
    if missing:
        raise ValueError(
            f"this figure needs a quadrotor trajectory (extras {missing} are missing); "
            "simulate a scenes.quadrotor(...) scene"
        )
    out = [np.asarray(traj.extras[n], dtype=np.float64) for n in names]
    if out[0].ndim != 2:
        raise ValueError(
            "plot functions take one run; index a batch first, e.g. "
            "jax.tree.map(lambda a: a[0], traj)"
        )
    return out


def quadrotor_figure(traj, title: str | None = None):
    """Tracking of a quadrotor run in four panels.

    Position against the desired one (altitude as ``-x_3``), the position error
    ``|e_x|``, the attitude error ``Psi = 1/2 tr(I - Rc^T R)``
    against the commanded attitude ``Rc`` (log scale, from machine epsilon: the
    trace formula's round-off, which can make ``Psi`` slightly negative), and the thrust ``f`` with
    the moments ``M``. Lee's model has no thrust limits: upside down, the
    commanded thrust is negative.

    **Arguments:**

    - `traj`: a `Trajectory` of a `scenes.quadrotor` scene (one run).
    - `title`: a figure title.

    **Returns:** the `Figure`.
    """
    import matplotlib.pyplot as plt

    x, x_d, e_x, psi, f = _extras(traj, "x", "x_d", "e_x", "Psi", "f")
    t = np.asarray(traj.t, dtype=np.float64)
    M = np.asarray(traj.M, dtype=np.float64)
    fig, ax = plt.subplots(2, 2, figsize=(11, 7), constrained_layout=True)
    sign = np.array([1.0, 1.0, -1.0])
    for i, (c, lab) in enumerate(zip(_AXIS_COLORS, ("x_1", "x_2", "-x_3 (up)"), strict=True)):
        ax[0, 0].plot(t, sign[i] * x[:, i], color=c, label=f"${lab}$" if i < 2 else lab)
        ax[0, 0].plot(t, sign[i] * x_d[:, i], "--", color=c, lw=1)
    ax[0, 0].set_title("position (solid) and desired (dashed)")
    ax[0, 0].set_ylabel("m")
    ax[0, 0].legend(fontsize=8)
    ax[0, 1].plot(t, np.linalg.norm(e_x, axis=-1))
    ax[0, 1].set_title(r"position error $|e_x|$")
    ax[0, 1].set_ylabel("m")
    # Psi from the trace formula: absolute round-off eps (a value < 0 shows at the floor).
    log_line(ax[1, 0], t, psi, floor=log_floor(np.asarray(traj.extras["Psi"]).dtype))
    ax[1, 0].set_title(r"attitude error $\Psi = \frac{1}{2}\,tr(I - R_c^T R)$")
    ax[1, 1].plot(t, f, color="k", label="thrust f [N]")
    ax[1, 1].set_ylabel("N")
    tw = ax[1, 1].twinx()
    for i, c in enumerate(_AXIS_COLORS):
        tw.plot(t, M[:, i], color=c, lw=1, label=f"$M_{i + 1}$")
    tw.set_ylabel("N m")
    ax[1, 1].set_title("thrust (black) and moments")
    tw.legend(fontsize=8, loc="upper right")
    for a in ax.ravel():
        a.set_xlabel("t [s]")
        a.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    return fig


def quadrotor_path(traj, title: str | None = None, n_frames: int = 12):
    """The 3-D path of a quadrotor run against the desired path, with body frames.

    Altitude is drawn up (``-x_3``). Every few points the thrust axis ``-R e3``
    is drawn as a short arrow, so a flip or a recovery shows as arrows turning over.

    **Arguments:**

    - `traj`: a `Trajectory` of a `scenes.quadrotor` scene (one run).
    - `title`: a figure title.
    - `n_frames`: number of thrust arrows along the path.

    **Returns:** the `Figure`.
    """
    import matplotlib.pyplot as plt

    x, x_d = _extras(traj, "x", "x_d")
    R = np.asarray(traj.R, dtype=np.float64)
    up = np.array([1.0, 1.0, -1.0])
    p, pd = x * up, x_d * up
    fig = plt.figure(figsize=(6.5, 5.5), constrained_layout=True)
    ax = fig.add_subplot(projection="3d")
    ax.plot(*pd.T, "--", color="gray", lw=1, label="desired")
    ax.plot(*p.T, color="tab:blue", lw=1.5, label="flown")
    both = np.concatenate([p, pd])
    lo, hi = both.min(axis=0), both.max(axis=0)
    span = max(float((hi - lo).max()), 1e-3)
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), 0.5 * (lo + hi), strict=True):
        setter(c - 0.55 * span, c + 0.55 * span)  # equal scales: turns look like turns
    idx = np.linspace(0, p.shape[0] - 1, n_frames).astype(int)
    thrust = -R[:, :, 2] * up  # -R e3, drawn with altitude up
    for i in idx:
        ax.quiver(*p[i], *(0.15 * span * thrust[i]), color="tab:red", lw=1)
    ax.set_xlabel("$x_1$ [m]")
    ax.set_ylabel("$x_2$ [m]")
    ax.set_zlabel("$-x_3$ (up) [m]")
    ax.legend(fontsize=8)
    ax.set_title(title or "path (red: thrust axis)")
    return fig
