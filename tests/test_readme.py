"""The README's example runs and prints what its comments say; its front matter stays in shape.

The example is executed as it stands (float64 on, as in the README). What it prints is
checked against references computed here: the initial attitude error from SciPy's
rotation of the same ZYX angles, the README's claims on the settled error and on the
orthogonality. The README's test command must be the one CI runs (`.ci/run`), its
"How fast" block must hold the markers `benchmarks/report.py` fills, and every local
file it links to must exist.
"""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")
PYTHON = re.compile(r"^```python\n(.*?)^```", re.DOTALL | re.MULTILINE)
LINK = re.compile(r"\]\(([^)\s]+)\)")
#: A work-session label (the pattern of `.ci/lint_tags.py`).
TAG = re.compile(r"(^|[^A-Za-z0-9_+/=])S[0-9]{2}[a-z]?\b")


def test_the_example_runs_and_prints_what_it_says():
    blocks = PYTHON.findall(README)
    assert len(blocks) == 1, "the README has one Python example"
    code = blocks[0]
    assert len(code.strip().splitlines()) <= 10, "the README's example is at most ten lines"
    printed = io.StringIO()
    namespace = {"__name__": "readme"}
    with contextlib.redirect_stdout(printed):
        exec(compile(code, "README.md", "exec"), namespace)
    lines = printed.getvalue().splitlines()
    assert len(lines) == 3, lines
    assert lines[0] == "finite to the end"
    psi0, psi2 = map(float, lines[1].split())
    # The seed starts at ZYX angles (pi/3, -pi/4, pi/6) with Rd(0) = I: Psi = (3 - tr R0) / 2.
    R0 = Rotation.from_euler("ZYX", [np.pi / 3, -np.pi / 4, np.pi / 6]).as_matrix()
    np.testing.assert_allclose(psi0, 0.5 * (3.0 - np.trace(R0)), rtol=0, atol=1e-12)
    assert f"{psi0:.3f}" == "0.954"  # the comment's figure
    traj = namespace["traj"]
    assert float(traj.t[200]) == 2.0  # psi[200] is t = 2 s (every tenth of 1 ms steps)
    assert 1e-7 < psi2 < 4e-7, psi2  # "~2e-7 at t = 2 s"
    ortho = float(lines[2])
    R = np.asarray(traj.R, dtype=np.float64)  # ||R^T R - I||_F, the largest over the run
    E = np.linalg.norm(np.swapaxes(R, -1, -2) @ R - np.eye(3), axis=(-2, -1)).max()
    np.testing.assert_allclose(ortho, E, rtol=0.1, atol=1e-15)
    assert ortho < 1e-13  # "~1e-14"


def test_the_test_command_is_what_ci_runs():
    block = re.search(r"```bash\n(.*?)```", README, re.DOTALL)
    assert block, "the README starts with a bash block of the two commands"
    commands = [ln for ln in block.group(1).splitlines() if ln and not ln.startswith("#")]
    assert len(commands) == 2, commands
    pytest_command = commands[1].split("&&")[-1].strip()
    assert pytest_command.startswith("python -m pytest"), pytest_command
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()
    assert pytest_command in ci, "CI (.ci/run) runs another test command than the README's"


def test_front_matter():
    lines = README.splitlines()
    assert len(lines) <= 200, f"README.md has {len(lines)} lines; keep it at 200 or fewer"
    assert lines[0] == "# so3jax" and lines[2], "a title, then a one-line tagline"
    assert README.count("<!-- report:how-fast -->") == 1
    assert README.count("<!-- /report:how-fast -->") == 1
    assert README.index("<!-- report:how-fast -->") < README.index("<!-- /report:how-fast -->")
    tagged = [ln for ln in lines if TAG.search(ln)]
    assert not tagged, f"session labels in README.md: {tagged}"


def test_local_links_exist():
    for target in LINK.findall(README):
        if re.match(r"[a-z]+://", target) or target.startswith("#"):
            continue
        path = target.split("#")[0]
        assert (ROOT / path).exists(), f"README.md links to {path}, which does not exist"
