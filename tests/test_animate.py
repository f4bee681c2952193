"""`plot.animate`: GIF animations of a run, and ``python -m so3jax --animate``."""

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

import so3jax as s
from so3jax import plot
from so3jax.__main__ import main

N = 5  # saved points of the hand-made runs


def _frames(path):
    """The frames of a GIF as RGB arrays."""
    with Image.open(path) as im:
        assert im.format == "GIF"
        out = []
        for k in range(im.n_frames):
            im.seek(k)
            out.append(np.asarray(im.convert("RGB"), dtype=np.int16))
    return out


def _assert_frames_differ(frames):
    for a, b in zip(frames, frames[1:], strict=False):
        assert np.abs(a - b).sum() > 0


def _trajectory(rotor_thrust=True):
    """A hand-made run: ``R(t) = exp(t w^)`` (SciPy), ``Rd`` about another axis; with
    ``quad``-style extras the vehicle flies a quarter circle above a dashed one."""
    t = np.linspace(0.0, 1.0, N)
    w = np.array([0.3, -1.2, 2.0])
    R = Rotation.from_rotvec(t[:, None] * w).as_matrix()
    Rd = Rotation.from_rotvec(t[:, None] * np.array([0.0, 0.0, 1.5])).as_matrix()
    Omega = np.tile(w, (N, 1))
    status = s.Status(code=jnp.asarray(0), step=jnp.asarray(-1))
    y = s.LieState(jnp.asarray(R[-1][None]), jnp.asarray(Omega[-1]))
    tracking = s.Trajectory(
        t=jnp.asarray(t),
        R=jnp.asarray(R),
        Omega=jnp.asarray(Omega),
        status=status,
        y=y,
        Rd=jnp.asarray(Rd),
        M=jnp.zeros((N, 3)),
    )
    phi = 0.5 * np.pi * t
    x = np.stack([np.cos(phi), np.sin(phi), -1.0 - 0.2 * t], -1)
    extras = {"x": jnp.asarray(x), "x_d": jnp.asarray(x * [1.0, 1.0, 0.0])}
    if rotor_thrust:
        extras["rotor_thrust"] = jnp.asarray(5.0 + np.outer(t, [1.0, -1.0, 2.0, 0.5]))
    quad = s.Trajectory(
        t=jnp.asarray(t),
        R=jnp.asarray(R),
        Omega=jnp.asarray(Omega),
        status=status,
        y=y,
        M=jnp.zeros((N, 3)),
        extras=extras,
    )
    return tracking, quad


def test_attitude_gif(tmp_path):
    tracking, _ = _trajectory()
    path = tmp_path / "seed.gif"
    assert plot.animate(tracking, path, fps=10) == path
    frames = _frames(path)
    assert len(frames) == N
    _assert_frames_differ(frames)
    # At most max_frames frames, spread over the run.
    frames = _frames(plot.animate(tracking, tmp_path / "few.gif", max_frames=3))
    assert len(frames) == 3


@pytest.mark.skipif(
    not __import__("matplotlib.animation").animation.writers.is_available("ffmpeg"),
    reason="writing an MP4 needs ffmpeg",
)
def test_attitude_mp4(tmp_path):
    """Where ffmpeg is present, an MP4 with one frame per saved point (ffmpeg decodes it
    and counts)."""
    import re
    import subprocess

    from matplotlib import rcParams

    tracking, _ = _trajectory()
    path = plot.animate(tracking, tmp_path / "seed.mp4", fps=10)
    decoded = subprocess.run(
        [rcParams["animation.ffmpeg_path"], "-i", str(path), "-map", "0:v:0", "-f", "null", "-"],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    assert int(re.findall(r"frame=\s*(\d+)", decoded.stderr)[-1]) == N


def test_quadrotor_gif(tmp_path):
    _, quad = _trajectory()
    rotors = s.Rotors(0.2, 0.02, 0.0, 18.0)
    scene = SimpleNamespace(rotors=rotors)  # animate reads only scene.rotors.arm
    path = str(tmp_path / "quad.gif")
    assert plot.animate(quad, path, scene=scene) == path
    frames = _frames(path)
    assert len(frames) == N
    _assert_frames_differ(frames)
    # Without rotor thrusts (and without a scene) the discs are drawn in one colour.
    _, quad = _trajectory(rotor_thrust=False)
    assert len(_frames(plot.animate(quad, tmp_path / "plain.gif", max_frames=2))) == 2


def test_bad_input(tmp_path, monkeypatch):
    tracking, _ = _trajectory()
    batch = jax.tree.map(lambda a: jnp.stack([a, a]), tracking)
    with pytest.raises(ValueError, match="one run"):
        plot.animate(batch, tmp_path / "b.gif")
    with pytest.raises(ValueError, match=r"\.gif"):
        plot.animate(tracking, tmp_path / "a.png")
    with pytest.raises(ValueError, match="max_frames"):
        plot.animate(tracking, tmp_path / "a.gif", max_frames=0)
    with pytest.raises(ValueError, match="fps"):
        plot.animate(tracking, tmp_path / "a.gif", fps=0)
    from matplotlib import animation

    monkeypatch.setattr(animation.writers, "is_available", lambda name: False)
    with pytest.raises(RuntimeError, match=r"ffmpeg.*\.gif"):
        plot.animate(tracking, tmp_path / "a.mp4")
    assert not list(tmp_path.iterdir())


def test_cli_animate(tmp_path, capsys):
    out, gif = tmp_path / "out", tmp_path / "anim" / "run.gif"
    argv = ["--dt", "0.01", "--duration", "0.03", "--no-plots", "--no-progress"]
    assert main([*argv, "--out", str(out), "--animate", str(gif)]) == 0
    frames = _frames(gif)
    assert len(frames) == 4  # t = 0, 0.01, 0.02, 0.03
    _assert_frames_differ(frames)
    assert str(gif) in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        main([*argv, "--out", str(out), "--animate", str(tmp_path / "run.avi")])
    assert e.value.code == 2
    assert "--animate" in capsys.readouterr().err
