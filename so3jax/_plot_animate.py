"""An animation of one run: the body frame turning, or the quadrotor flying its path.

`animate` draws one frame per selected saved point into a single figure and hands
each frame to a matplotlib movie writer: ``PillowWriter`` for a GIF (Pillow comes
with matplotlib), ``FFMpegWriter`` for an MP4 (needs the ``ffmpeg`` program).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

_AXIS_COLORS = ("tab:red", "tab:green", "tab:blue")
#: Arm length (m) drawn for a quadrotor whose scene does not say (no `Rotors`).
DEFAULT_ARM = 0.3
#: World to drawing: ``e3`` points down, the drawing shows the altitude ``-x_3`` up.
_UP = np.array([1.0, 1.0, -1.0])


def check_path(path) -> Path:
    """``path`` as a `Path` whose suffix names an available writer (``.gif``, ``.mp4``).

    **Raises:** `ValueError` for another suffix; `RuntimeError` for ``.mp4``
    without ``ffmpeg``.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".gif":
        return path
    if suffix == ".mp4":
        from matplotlib import animation

        if not animation.writers.is_available("ffmpeg"):
            raise RuntimeError(
                f"path {str(path)!r}: writing an MP4 needs matplotlib's 'ffmpeg' writer "
                "(the ffmpeg program on PATH), which is not available; write a .gif instead"
            )
        return path
    raise ValueError(
        f"path must end in .gif (PillowWriter) or .mp4 (FFMpegWriter, needs ffmpeg), "
        f"got {str(path)!r}"
    )


def _writer(path: Path, fps: float):
    from matplotlib import animation

    if path.suffix.lower() == ".gif":
        return animation.PillowWriter(fps=fps)
    return animation.FFMpegWriter(fps=fps)


def _frames(n: int, max_frames: int) -> np.ndarray:
    """At most ``max_frames`` saved-point indices, evenly spread, first and last included."""
    k = min(n, max_frames)
    return np.unique(np.round(np.linspace(0, n - 1, k)).astype(int))


def _extra(traj, name):
    a = traj.extras.get(name) if traj.extras else None
    return None if a is None else np.asarray(a, dtype=np.float64)


def _limits(ax, points: np.ndarray, margin: float) -> None:
    """Equal scales on the three axes around the finite ``points`` (shape `(m, 3)`)."""
    finite = points[np.all(np.isfinite(points), axis=-1)]
    if finite.size == 0:
        finite = np.zeros((1, 3))
    lo, hi = finite.min(axis=0), finite.max(axis=0)
    half = 0.5 * float((hi - lo).max()) + margin
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), 0.5 * (lo + hi), strict=True):
        setter(c - half, c + half)
    ax.set_box_aspect((1, 1, 1))


class _AttitudeFrames:
    """The body frame (columns of ``R``) as arrows from the origin; ``Rd`` dashed."""

    def __init__(self, ax, R, Rd):
        self.ax, self.R, self.Rd = ax, R, Rd
        self.arrows = None
        self.ref = []
        if Rd is not None:
            for i, c in enumerate(_AXIS_COLORS):
                (line,) = ax.plot([], [], [], ls="--", color=c, alpha=0.5, lw=1.5)
                line.set_label("reference" if i == 0 else None)
                self.ref.append(line)
        for i, c in enumerate(_AXIS_COLORS):  # legend entries for the arrows
            ax.plot([], [], [], color=c, lw=2, label=f"body $e_{i + 1}$")
        _limits(ax, np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), 0.05)
        ax.set_xlabel("x")
        ax.set_ylabel("y")
        ax.set_zlabel("z")
        ax.legend(fontsize=8, loc="upper left")

    def draw(self, k: int) -> None:
        if self.arrows is not None:
            self.arrows.remove()
        axes = self.R[k].T  # rows: R e1, R e2, R e3
        zero = np.zeros((3, 3))
        self.arrows = self.ax.quiver(
            *zero.T, *axes.T, colors=list(_AXIS_COLORS), lw=2.5, arrow_length_ratio=0.15
        )
        for i, line in enumerate(self.ref):
            tip = self.Rd[k][:, i]
            line.set_data_3d([0.0, tip[0]], [0.0, tip[1]], [0.0, tip[2]])


def _disc(centre, u, v, radius, m=24):
    """Points of a circle of ``radius`` about ``centre`` in the plane of unit ``u``, ``v``."""
    s = np.linspace(0.0, 2.0 * np.pi, m, endpoint=False)
    return centre + radius * (np.cos(s)[:, None] * u + np.sin(s)[:, None] * v)


class _QuadrotorFrames:
    """Arms along ``b1``, ``b2`` through the centre, rotor discs at the tips, the path so far."""

    def __init__(self, ax, R, x, x_d, thrust, arm):
        import matplotlib as mpl
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection

        self.ax, self.arm = ax, arm
        self.p = x * _UP  # drawing coordinates: altitude up
        self.B = R * _UP[:, None]  # body axes in drawing coordinates (columns)
        self.thrust = thrust
        if thrust is not None:
            finite = thrust[np.isfinite(thrust)]
            lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
            self.norm = mpl.colors.Normalize(lo, hi if hi > lo else lo + 1.0)
            self.cmap = mpl.colormaps["viridis"]
        points = [self.p]
        if x_d is not None:
            pd = x_d * _UP
            points.append(pd)
            ax.plot(*pd.T, "--", color="gray", lw=1, label="reference")
        (self.path,) = ax.plot([], [], [], color="tab:blue", lw=1.5, label="flown")
        self.arms = [ax.plot([], [], [], color=c, lw=2.5)[0] for c in _AXIS_COLORS[:2]]
        (self.up,) = ax.plot([], [], [], color="k", lw=1)
        self.discs = Poly3DCollection([np.zeros((3, 3))] * 4, edgecolor="k", linewidths=0.5)
        ax.add_collection3d(self.discs)
        if thrust is not None:
            sm = mpl.cm.ScalarMappable(norm=self.norm, cmap=self.cmap)
            ax.figure.colorbar(sm, ax=ax, shrink=0.6, pad=0.1, label="rotor thrust [N]")
        _limits(ax, np.concatenate(points), 1.3 * arm)
        ax.set_xlabel("$x_1$ [m]")
        ax.set_ylabel("$x_2$ [m]")
        ax.set_zlabel("$-x_3$ (up) [m]")
        ax.legend(fontsize=8, loc="upper left")

    def draw(self, k: int) -> None:
        c, B, d = self.p[k], self.B[k], self.arm
        b1, b2, b3 = B[:, 0], B[:, 1], B[:, 2]
        for line, b in zip(self.arms, (b1, b2), strict=True):
            ends = np.stack([c - d * b, c + d * b])
            line.set_data_3d(*ends.T)
        ends = np.stack([c, c - 0.5 * d * b3])  # the thrust axis -R e3
        self.up.set_data_3d(*ends.T)
        self.path.set_data_3d(*self.p[: k + 1].T)
        # Rotors 1-4 on b1, b2, -b1, -b2 (Lee, Leok & McClamroch's '+' layout).
        tips = (c + d * b1, c + d * b2, c - d * b1, c - d * b2)
        self.discs.set_verts([_disc(tip, b1, b2, 0.35 * d) for tip in tips])
        if self.thrust is None:
            self.discs.set_facecolor((0.6, 0.6, 0.6, 0.7))
        else:
            colors = self.cmap(self.norm(np.nan_to_num(self.thrust[k], nan=self.norm.vmin)))
            colors[:, 3] = 0.8
            self.discs.set_facecolor(colors)


def animate(traj, path, *, fps: float = 20, max_frames: int = 120, scene=None):
    """Write an animation of one run to a GIF or an MP4 file.

    A quadrotor run (``x`` in ``traj.extras``) shows the vehicle flying, altitude
    ``-x_3`` up: its two arms as segments through the centre along the body axes
    ``b1`` (red) and ``b2`` (green), a short black line along the thrust axis
    ``-R e3``, four rotor discs at the arm tips (rotors 1-4 on ``b1``, ``b2``,
    ``-b1``, ``-b2``) shaded by ``extras["rotor_thrust"]`` when the run saved it
    (one colour scale for the whole run, else uniform grey), the path flown so
    far and the reference path ``x_d`` (dashed). Any other run shows the body
    frame, the columns of ``R`` as red, green and blue arrows from the origin,
    and the reference frame ``Rd`` (same colours, dashed) when the run has one.
    The title gives the time of the frame.

    The frames are at most `max_frames` saved points spread evenly over the run,
    the first and the last included. Points past a failure (NaN) draw nothing.

    **Arguments:**

    - `traj`: a `Trajectory` of one run (``traj.R`` of shape `(n, 3, 3)`).
    - `path`: the file to write: ``.gif`` (matplotlib's ``PillowWriter``) or
      ``.mp4`` (``FFMpegWriter``, needs ``ffmpeg``).
    - `fps`: frames per second of the file (> 0).
    - `max_frames`: the most frames to draw (>= 1).
    - `scene`: the scene of the run, optional: a quadrotor's arm length is
      ``scene.rotors.arm`` when it has `Rotors`, else 0.3 m.

    **Returns:** `path`.

    **Raises:** `ValueError` for a batch of runs, another suffix than ``.gif`` or
    ``.mp4``, or a bad `fps` / `max_frames`; `RuntimeError` for ``.mp4``
    without ``ffmpeg``.
    """
    import matplotlib.pyplot as plt

    out = check_path(path)
    if isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)):
        raise ValueError(f"max_frames must be an integer >= 1, got {max_frames!r}")
    if max_frames < 1:
        raise ValueError(f"max_frames must be an integer >= 1, got {max_frames}")
    if not (isinstance(fps, (int, float, np.number)) and math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive finite number, got {fps!r}")
    R = np.asarray(traj.R, dtype=np.float64)
    if R.ndim != 3:
        raise ValueError(
            f"animate takes one run (traj.R of shape (n, 3, 3)), got shape {R.shape}; "
            "pick one run first, e.g. jax.tree.map(lambda a: a[0], traj)"
        )
    t = np.asarray(traj.t, dtype=np.float64)
    x = _extra(traj, "x")
    fig = plt.figure(figsize=(5.5, 5), dpi=80)
    try:
        ax = fig.add_subplot(projection="3d")
        if x is not None:
            rotors = getattr(scene, "rotors", None)
            arm = DEFAULT_ARM if rotors is None else float(np.asarray(rotors.arm))
            frames = _QuadrotorFrames(
                ax, R, x, _extra(traj, "x_d"), _extra(traj, "rotor_thrust"), arm
            )
        else:
            Rd = None if traj.Rd is None else np.asarray(traj.Rd, dtype=np.float64)
            frames = _AttitudeFrames(ax, R, Rd)
        out.parent.mkdir(parents=True, exist_ok=True)
        writer = _writer(out, fps)
        with writer.saving(fig, str(out), dpi=fig.dpi):
            for k in _frames(R.shape[0], int(max_frames)):
                frames.draw(int(k))
                ax.set_title(f"t = {t[k]:.3f} s")
                writer.grab_frame()
    finally:
        plt.close(fig)
    return path
