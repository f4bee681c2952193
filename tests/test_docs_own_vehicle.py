"""The code of ``docs/own-vehicle.md`` runs, and does what the page says it does.

The page's ```` ```python ```` blocks are executed in order in one namespace (float64
on, as ``conftest.py`` sets it), so the page cannot go stale: what each block prints
must match the ```` ```text ```` block shown under it (numbers to 1 %, round-off below
1e-9 as any round-off). The tests then check the facts the page states against
references computed here independently: SciPy for the slew's target, the torque bound for
the clipped controller, a plain ``vmap`` of ``simulate`` for the tuned cost.
"""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import so3jax

PAGE = Path(__file__).resolve().parents[1] / "docs" / "own-vehicle.md"
# A python block, and the text block right under it (its shown output), if any.
BLOCK = re.compile(r"^```python\n(.*?)^```\n(?:\n```text\n(.*?)^```)?", re.DOTALL | re.MULTILINE)
NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:e[-+]?\d+)?|(?<![a-z])[-+]?inf(?![a-z])")
ROUND_OFF = 1e-9


def python_blocks(text: str) -> list[tuple[str, str | None]]:
    """The page's ```` ```python ```` blocks in order, each with the output shown under it."""
    return [(code, shown or None) for code, shown in BLOCK.findall(text)]


def _same_output(printed: str, shown: str) -> bool:
    """Equal text, numbers within 1 % (both below `ROUND_OFF` in size: round-off, equal)."""
    got, want = printed.split(), shown.split()
    if len(got) != len(want):
        return False
    for a, b in zip(got, want, strict=True):
        na, nb = NUMBER.findall(a), NUMBER.findall(b)
        if NUMBER.sub("#", a) != NUMBER.sub("#", b) or len(na) != len(nb):
            return False
        for x, y in zip(map(float, na), map(float, nb), strict=True):
            if not (max(abs(x), abs(y)) < ROUND_OFF or x == y or abs(x - y) <= 0.01 * abs(y)):
                return False
    return True


@pytest.fixture(scope="module")
def page():
    """The namespace after running every block, and what each block printed and shows."""
    blocks = python_blocks(PAGE.read_text(encoding="utf-8"))
    assert len(blocks) >= 8, f"expected the page's code blocks in {PAGE}"
    namespace = {"__name__": "own_vehicle"}
    outputs = []
    for i, (code, shown) in enumerate(blocks):
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            exec(compile(code, f"{PAGE.name}, block {i}", "exec"), namespace)
        outputs.append((printed.getvalue(), shown))
    return namespace, outputs


def test_shown_outputs_are_what_the_code_prints(page):
    _, outputs = page
    for i, (printed, shown) in enumerate(outputs):
        if shown is None:
            assert not printed, f"block {i} prints, but the page shows no output under it"
            continue
        assert _same_output(printed, shown), (
            f"block {i} of {PAGE.name} printed\n{printed}\nbut the page shows\n{shown}"
        )


def test_inertia_is_the_full_tensor(page):
    ns, _ = page
    np.testing.assert_allclose(np.asarray(ns["body"].inertia), ns["J"], rtol=0, atol=1e-15)
    assert np.count_nonzero(ns["J"] - np.diag(np.diag(ns["J"]))) == 6  # products of inertia


def test_slew_ends_at_its_target(page):
    ns, _ = page
    # Rd0 exp(angle n) from SciPy: intrinsic ZYX angles, then the slew about body z.
    Rd0 = Rotation.from_euler("ZYX", [0.3, -0.1, 0.2])
    target = (Rd0 * Rotation.from_rotvec(np.pi / 2 * np.array([0.0, 0.0, 1.0]))).as_matrix()
    traj = ns["traj"]
    assert traj.status.message() == "finite to the end"
    np.testing.assert_allclose(np.asarray(traj.Rd[-1]), target, atol=1e-12)  # closed form
    np.testing.assert_allclose(np.asarray(traj.R[-1]), target, atol=1e-6)
    # The Euler angles the page prints, against SciPy's.
    np.testing.assert_allclose(
        np.asarray(so3jax.to_euler("ZYX", traj.R[-1])),
        Rotation.from_matrix(target).as_euler("ZYX"),
        atol=1e-6,
    )


def test_clipped_torque_respects_its_bound(page):
    ns, _ = page
    bound = np.asarray(ns["max_torque"])
    M_free, M_sat = np.asarray(ns["traj"].M), np.asarray(ns["traj_sat"].M)
    assert (np.abs(M_free) > bound).any(), "the unclipped slew should exceed the bound"
    assert (np.abs(M_sat) <= bound + 1e-15).all()
    assert np.isclose(np.abs(M_sat).max(), bound.max())  # the clip was active
    # Still on target at the end, within the page's statement (0.015 degrees).
    assert float(np.degrees(ns["miss_sat"])) < 0.05
    # The sweep ran the clipped controller too: no run's |M| exceeds |max_torque|.
    result = ns["result"]
    assert result.max_peak_torque.max() <= np.linalg.norm(bound) * (1 + 1e-12)
    assert result.outcome_counts()["diverged"] == 0


def test_tuned_cost_is_below_the_initial_one(page):
    ns, _ = page
    tuned, my_cost, starts = ns["tuned"], ns["my_cost"], ns["starts"]
    assert tuned.cost < tuned.initial_cost
    assert tuned.cost_history[-1] < tuned.cost_history[0]

    # The same mean cost, recomputed here from plain simulations of each start.
    def mean_cost(gains):
        scene = so3jax.scenes.tracking(
            ns["J"],
            ns["SaturatedController"](gains, ns["max_torque"]),
            starts[0],
            ns["Omega0"],  # tune keeps the scene's initial rate
            ns["Rd0"],
            reference=ns["slew"],
        )
        run = jax.vmap(lambda R0: my_cost(so3jax.simulate(scene, so3jax.RKMK4(), 0.02, 300, R0=R0)))
        return float(jnp.mean(run(starts)))

    assert mean_cost(tuned.gains) == pytest.approx(tuned.cost, rel=1e-9)
    assert mean_cost(so3jax.GeometricGains(0.4, 0.6)) == pytest.approx(tuned.initial_cost, rel=1e-9)


def test_bad_start_is_named_in_the_status(page):
    ns, outputs = page
    printed = "".join(out for out, _ in outputs)
    batch = ns["batch"]
    np.testing.assert_array_equal(np.asarray(batch.status.code), [0, 0, 11, 0])
    assert "1 run: the initial attitude R0 is not a rotation" in batch.status.message()
    assert np.isnan(np.asarray(batch.R[2])).all()
    assert "inertia must be symmetric" in printed
    assert "triangle inequality" in printed
