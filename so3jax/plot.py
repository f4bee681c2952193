"""Figures of a `Trajectory` (matplotlib), reusable from notebooks and scripts.

Every function takes a `Trajectory` (one run, not a batch) and returns a
`matplotlib.figure.Figure`; the single-panel ones draw into ``ax`` when given.
Scripts that only write files should select the Agg backend first
(``matplotlib.use("Agg")``), as ``python -m so3jax`` does.
`animate` writes a run as a GIF or an MP4 file instead and returns its path.

Quantities:

- ``Psi = 1/2 tr(I - Rd^T R) = 1 - cos(angle)``, evaluated as
  ``2 sin^2(angle / 2)`` with the angle from ``atan2`` so that it stays
  accurate down to round-off (the trace formula bottoms out at ~1e-16).
- the seed's normalised distance ``||R - Rd||_F / (2 sqrt 2)`` in ``[0, 1]``.
- ``|e_Omega|``, the torque ``M``, the orthogonality error ``||R^T R - I||_F``.

Log panels start at a floor set by the data type's machine epsilon (values below
it, zeros included, are drawn at the floor and the axis never goes lower):
``eps^2`` for ``Psi`` (it resolves angles down to ``eps``), ``eps`` for the
distance, ``eps`` times the run's largest ``|Omega|`` or ``|e_Omega|`` for
``|e_Omega|``, and ``eps / 100`` for the panels that draw machine epsilon as a
reference line (orthogonality, conservation and constraint errors).
"""

from __future__ import annotations

import numpy as np

# Figures of a quadrotor run, and of a `SweepResult` and a `TuneResult`, and the
# animation of a run live in their own modules.
from ._plot_animate import animate as animate
from ._plot_log import log_floor, log_line, peak
from ._plot_quadrotor import quadrotor_figure as quadrotor_figure, quadrotor_path as quadrotor_path
from ._plot_sweep import (
    settling_distribution as settling_distribution,
    sweep_heatmaps as sweep_heatmaps,
    tune_figure as tune_figure,
    worst_attitudes as worst_attitudes,
)

__all__ = [
    "sweep_heatmaps",
    "settling_distribution",
    "worst_attitudes",
    "tune_figure",
    "quadrotor_figure",
    "quadrotor_path",
    "animate",
    "attitude_error",
    "angular_velocity_error",
    "torque",
    "orthogonality",
    "tracking_figure",
    "free_body_figure",
    "suslov_figure",
    "body_axes_figure",
    "error_function",
    "normalized_distance",
]

_AXIS_COLORS = ("tab:red", "tab:green", "tab:blue")


def _np(x):
    return None if x is None else np.asarray(x, dtype=np.float64)


def _check_single(traj):
    R = _np(traj.R)
    if R.ndim != 3:
        raise ValueError(
            f"plot functions take one run (traj.R of shape (n, 3, 3)), got shape {R.shape}; "
            "index a batch first, e.g. jax.tree.map(lambda a: a[0], traj)"
        )
    return R


def error_function(R, Rd) -> np.ndarray:
    """``Psi(R, Rd) = 1 - cos(angle of Rd^T R)``, accurate near zero (NumPy).

    **Arguments:**

    - `R`, `Rd`: rotations, shape `(..., 3, 3)`.

    **Returns:** shape `(...)`, in ``[0, 2]``.
    """
    R, Rd = _np(R), _np(Rd)
    E = np.swapaxes(Rd, -1, -2) @ R
    s = 0.5 * np.stack(
        [E[..., 2, 1] - E[..., 1, 2], E[..., 0, 2] - E[..., 2, 0], E[..., 1, 0] - E[..., 0, 1]],
        -1,
    )
    c = 0.5 * (np.trace(E, axis1=-2, axis2=-1) - 1.0)
    angle = np.arctan2(np.linalg.norm(s, axis=-1), c)
    return 2.0 * np.sin(0.5 * angle) ** 2


def normalized_distance(R, Rd) -> np.ndarray:
    """The seed's ``||R - Rd||_F / (2 sqrt 2)`` in ``[0, 1]`` (``= sqrt(Psi / 2)``)."""
    D = _np(R) - _np(Rd)
    return np.sqrt(np.sum(D * D, axis=(-1, -2))) / (2.0 * np.sqrt(2.0))


def _orth(R) -> np.ndarray:
    E = np.swapaxes(R, -1, -2) @ R - np.eye(3)
    return np.sqrt(np.sum(E * E, axis=(-1, -2)))


def _axes(ax, **subplots):
    import matplotlib.pyplot as plt

    if ax is None:
        fig, ax = plt.subplots(**subplots)
        return fig, ax
    return ax.figure, ax


def _dtype(a):
    """The floating type the plotted data were computed in (before `_np` widens it)."""
    return np.asarray(a).dtype


def _need_tracking(traj, what):
    if traj.Rd is None:
        raise ValueError(f"{what} needs a tracking trajectory (traj.Rd is None)")


def attitude_error(traj, ax=None):
    """``Psi(t)`` (log scale) and the normalised distance ``||R - Rd|| / (2 sqrt 2)``.

    **Arguments:**

    - `traj`: a `Trajectory` of a tracking scene (with ``Rd``).
    - `ax`: a matplotlib ``Axes`` to draw into (default: a new figure).

    **Returns:** the `Figure`.
    """
    _need_tracking(traj, "attitude_error")
    R = _check_single(traj)
    t, Rd = _np(traj.t), _np(traj.Rd)
    fig, ax = _axes(ax, figsize=(6, 3.5))
    dtype = _dtype(traj.R)
    eps = log_floor(dtype)
    log_line(
        ax,
        t,
        error_function(R, Rd),
        floor=log_floor(dtype, eps),
        label=r"$\Psi = \frac{1}{2}\,tr(I - R_d^T R)$",
    )
    log_line(
        ax, t, normalized_distance(R, Rd), "--", floor=eps, label=r"$\|R - R_d\|_F / (2\sqrt{2})$"
    )
    ax.set_xlabel("t [s]")
    ax.set_ylabel("attitude error")
    ax.set_title("Attitude error")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def angular_velocity_error(traj, ax=None):
    """``|e_Omega|(t)`` (log scale); ``|Omega|`` for scenes without a reference.

    **Arguments:**

    - `traj`: a `Trajectory` (``e_Omega`` is read from ``traj.extras``).
    - `ax`: a matplotlib ``Axes`` (default: a new figure).

    **Returns:** the `Figure`.
    """
    _check_single(traj)
    t = _np(traj.t)
    fig, ax = _axes(ax, figsize=(6, 3.5))
    if "e_Omega" in traj.extras:
        raw, label = traj.extras["e_Omega"], r"$|e_\Omega|$"
    else:
        raw, label = traj.Omega, r"$|\Omega|$"
    y = np.linalg.norm(_np(raw), axis=-1)
    # e_Omega = Omega - R^T Rd Omega_d carries the round-off of |Omega|.
    scale = peak(y, np.linalg.norm(_np(traj.Omega), axis=-1))
    log_line(ax, t, y, floor=log_floor(_dtype(raw), scale), label=label)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("rad/s")
    ax.set_title("Angular-velocity error")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def torque(traj, ax=None):
    """Control torques ``M_1, M_2, M_3`` over time.

    **Arguments:**

    - `traj`: a `Trajectory` with ``M`` (a tracking scene).
    - `ax`: a matplotlib ``Axes`` (default: a new figure).

    **Returns:** the `Figure`.
    """
    if traj.M is None:
        raise ValueError("torque needs a trajectory with torques (traj.M is None)")
    _check_single(traj)
    t, M = _np(traj.t), _np(traj.M)
    fig, ax = _axes(ax, figsize=(6, 3.5))
    for i in range(3):
        ax.plot(t, M[:, i], color=_AXIS_COLORS[i], label=f"$M_{i + 1}$")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("N m")
    ax.set_title("Control torque")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def orthogonality(traj, ax=None):
    """Distance from the group ``||R^T R - I||_F`` (and for ``Rd``) over time.

    **Arguments:**

    - `traj`: a `Trajectory`.
    - `ax`: a matplotlib ``Axes`` (default: a new figure).

    **Returns:** the `Figure`.
    """
    R = _check_single(traj)
    t = _np(traj.t)
    fig, ax = _axes(ax, figsize=(6, 3.5))
    eps = log_floor(_dtype(traj.R))
    log_line(ax, t, _orth(R), floor=eps / 100, label=r"$\|R^T R - I\|_F$")
    if traj.Rd is not None:
        Rd = _np(traj.Rd)
        log_line(ax, t, _orth(Rd), "--", floor=eps / 100, label=r"$\|R_d^T R_d - I\|_F$")
    ax.axhline(eps, color="gray", lw=0.8, ls=":", label="machine epsilon")
    ax.set_xlabel("t [s]")
    ax.set_title("Orthogonality error")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def tracking_figure(traj, title: str | None = None):
    """The four tracking panels: ``Psi`` and distance, ``|e_Omega|``, ``M``, orthogonality.

    **Arguments:**

    - `traj`: a `Trajectory` of a tracking scene.
    - `title`: a figure title.

    **Returns:** the `Figure` (2 x 2 panels).
    """
    import matplotlib.pyplot as plt

    _need_tracking(traj, "tracking_figure")
    fig, axs = plt.subplots(2, 2, figsize=(11, 7), constrained_layout=True)
    attitude_error(traj, axs[0, 0])
    angular_velocity_error(traj, axs[0, 1])
    torque(traj, axs[1, 0])
    orthogonality(traj, axs[1, 1])
    if title:
        fig.suptitle(title)
    return fig


def free_body_figure(traj, body=None, title: str | None = None):
    """Panels for a torque-free run: ``Omega``, conservation errors, orthogonality.

    **Arguments:**

    - `traj`: a `Trajectory`.
    - `body`: the `RigidBody` (for the energy and angular momentum panel;
      without it that panel shows ``|Omega|``).
    - `title`: a figure title.

    **Returns:** the `Figure` (3 panels).
    """
    import matplotlib.pyplot as plt

    R = _check_single(traj)
    t, Om = _np(traj.t), _np(traj.Omega)
    fig, axs = plt.subplots(1, 3, figsize=(14, 3.8), constrained_layout=True)
    for i in range(3):
        axs[0].plot(t, Om[:, i], color=_AXIS_COLORS[i], label=rf"$\Omega_{i + 1}$")
    axs[0].set_title("Body angular velocity")
    axs[0].set_xlabel("t [s]")
    axs[0].set_ylabel("rad/s")
    axs[0].legend(fontsize=8)
    axs[0].grid(True, alpha=0.3)
    ax = axs[1]
    eps = log_floor(_dtype(traj.R))
    if body is not None:
        J = _np(body.inertia)
        T = 0.5 * np.einsum("ni,ij,nj->n", Om, J, Om)
        pi = np.einsum("nij,jk,nk->ni", R, J, Om)
        dT = np.abs(T / T[0] - 1)
        dpi = np.linalg.norm(pi - pi[0], axis=-1) / max(np.linalg.norm(pi[0]), 1e-300)
        log_line(ax, t, dT, floor=eps / 100, label="energy (relative)")
        log_line(ax, t, dpi, floor=eps / 100, label="spatial momentum (relative)")
        ax.set_title("Conservation errors")
    else:
        ax.plot(t, np.linalg.norm(Om, axis=-1), label=r"$|\Omega|$")
        ax.set_title(r"$|\Omega|$")
    ax.set_xlabel("t [s]")
    ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)
    orthogonality(traj, axs[2])
    if title:
        fig.suptitle(title)
    return fig


def suslov_figure(traj, scene, title: str | None = None):
    """Panels for a run of Suslov's body: ``Omega``, energy, constraint, ``|J Omega|``.

    ``Omega`` by component; the relative energy error ``|T / T0 - 1|`` (the flow
    conserves ``T``); the constraint residual ``|<Omega, a>|`` against machine
    epsilon; and ``|J Omega|``, which the free body would keep (dashed) and the
    constraint torque changes.

    **Arguments:**

    - `traj`: a `Trajectory` of a `scenes.Suslov` scene.
    - `scene`: that scene (for ``J`` and ``a``).
    - `title`: a figure title.

    **Returns:** the `Figure` (2 x 2 panels).
    """
    import matplotlib.pyplot as plt

    _check_single(traj)
    t, Om = _np(traj.t), _np(traj.Omega)
    J, a = _np(scene.body.inertia), _np(scene.a)
    eps = log_floor(_dtype(traj.Omega))
    fig, axs = plt.subplots(2, 2, figsize=(11, 7), constrained_layout=True)
    ax = axs[0, 0]
    for i in range(3):
        ax.plot(t, Om[:, i], color=_AXIS_COLORS[i], label=rf"$\Omega_{i + 1}$")
    ax.set_title("Body angular velocity")
    ax.set_ylabel("rad/s")
    ax = axs[0, 1]
    T = 0.5 * np.einsum("ni,ij,nj->n", Om, J, Om)
    log_line(ax, t, np.abs(T / T[0] - 1), floor=eps / 100, label=r"$|T/T_0 - 1|$")
    ax.set_title("Energy error (relative)")
    ax = axs[1, 0]
    res = np.abs(Om @ a) / max(np.linalg.norm(Om[0]), 1e-300)
    log_line(ax, t, res, floor=eps / 100, label=r"$|\langle\Omega, a\rangle| / |\Omega_0|$")
    ax.axhline(eps, color="gray", lw=0.8, ls=":", label="machine epsilon")
    ax.set_title("Constraint residual")
    ax = axs[1, 1]
    L = np.linalg.norm(Om @ J.T, axis=-1)
    ax.plot(t, L, label=r"$|J\Omega|$")
    ax.axhline(L[0], color="gray", lw=0.8, ls="--", label="initial (kept by a free body)")
    ax.set_title(r"$|J\Omega|$: the broken Casimir")
    for ax in axs.flat:
        ax.set_xlabel("t [s]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    return fig


def body_axes_figure(traj, title: str | None = None):
    """Orientation over time: the tips of the body axes ``R e_i`` on the unit sphere.

    Solid curves are the body axes (red, green, blue for ``e1, e2, e3``; a
    circle marks the start, a star the end); dashed grey curves the reference
    axes ``Rd e_i`` when the trajectory has them. The right panel shows the
    same tips' coordinates against time.

    **Arguments:**

    - `traj`: a `Trajectory`.
    - `title`: a figure title.

    **Returns:** the `Figure`.
    """
    import matplotlib.pyplot as plt

    R = _check_single(traj)
    t = _np(traj.t)
    fig = plt.figure(figsize=(12, 5.5), constrained_layout=True)
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    u, v = np.mgrid[0 : 2 * np.pi : 37j, 0 : np.pi : 19j]
    ax.plot_wireframe(np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v), color="0.85", lw=0.4)
    if traj.Rd is not None:
        Rd = _np(traj.Rd)
        for i in range(3):
            tip = Rd[:, :, i]
            ax.plot(
                *tip.T, ls="--", color="0.4", lw=1.0, label="reference axes" if i == 0 else None
            )
    for i in range(3):
        tip = R[:, :, i]
        c = _AXIS_COLORS[i]
        ax.plot(*tip.T, color=c, lw=1.4, label=f"body $e_{i + 1}$")
        ax.scatter(*tip[0], color=c, marker="o", s=30)
        ax.scatter(*tip[-1], color=c, marker="*", s=90)
    ax.set_xlim(-1, 1)
    ax.set_ylim(-1, 1)
    ax.set_zlim(-1, 1)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title("Body axes on the unit sphere (o start, * end)")
    axs = fig.add_subplot(1, 2, 2)
    for i in range(3):
        for j, ls in enumerate(("-", "--", ":")):
            axs.plot(
                t,
                R[:, j, i],
                color=_AXIS_COLORS[i],
                ls=ls,
                lw=1.0,
                label=f"$(R e_{i + 1})_{'xyz'[j]}$",
            )
    axs.set_xlabel("t [s]")
    axs.set_title("Body-axis coordinates in the world frame")
    axs.legend(fontsize=7, ncol=3)
    axs.grid(True, alpha=0.3)
    if title:
        fig.suptitle(title)
    return fig
