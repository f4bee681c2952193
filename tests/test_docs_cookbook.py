"""The recipes of ``docs/cookbook.md`` run as they stand, and do what the page says.

Each ```` ```python ```` block is a recipe that runs on its own, in a fresh namespace;
a block under a ``<!-- cookbook: not run ... -->`` comment (one that needs several
processes) is only compiled. The tests then check each recipe's result against a
reference computed here: NumPy for the swept body's inertia, a plain ``vmap`` of
``simulate`` for the tuned cost, and the methods' orders of convergence for the
integrator comparison.
"""

from __future__ import annotations

import contextlib
import inspect
import io
import re
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import so3jax

PAGE = Path(__file__).resolve().parents[1] / "docs" / "cookbook.md"
BLOCK = re.compile(r"(<!-- cookbook: not run[^>]*-->\n)?^```python\n(.*?)^```", re.S | re.M)


def _recipes():
    return [(code, bool(skip)) for skip, code in BLOCK.findall(PAGE.read_text(encoding="utf-8"))]


@pytest.fixture(scope="module")
def recipes():
    """Each recipe's namespace and what it printed (``None`` for a recipe not run)."""
    found = _recipes()
    assert len(found) == 4, f"expected the four Python recipes of {PAGE}"
    out = []
    for i, (code, skip) in enumerate(found):
        compiled = compile(code, f"{PAGE.name}, recipe {i}", "exec")
        if skip:
            out.append((None, None))
            continue
        namespace = {"__name__": f"cookbook_{i}"}
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            exec(compiled, namespace)
        out.append((namespace, printed.getvalue()))
    return out


def test_sweep_my_own_vehicle(recipes):
    ns, printed = recipes[0]
    J = ns["J"]
    assert np.allclose(np.asarray(ns["scene"].body.inertia), J)
    # The body's principal moments are the tensor's eigenvalues (NumPy's).
    moments = np.linalg.eigvalsh(np.asarray(ns["scene"].body.inertia))
    np.testing.assert_allclose(moments, np.linalg.eigvalsh(J), rtol=1e-12)
    result = ns["result"]
    assert result.final_psi.shape == (9, 4)  # 3 x 3 gain pairs x 4 starts
    best = result.best()
    assert float(result.mean_cost[best]) == float(np.nanmin(result.mean_cost))
    assert "settled" in printed


def test_tune_on_my_own_cost(recipes):
    ns, _ = recipes[1]
    res, starts, my_cost = ns["res"], ns["starts"], ns["my_cost"]
    seed = so3jax.scenes.seed()

    def mean_cost(k_R, k_Omega):  # the recipe's cost over its starts, with a plain vmap
        gains = so3jax.GeometricGains(k_R=k_R, k_Omega=k_Omega)
        scene = eqx.tree_at(lambda s: s.controller.gains, seed, gains)

        def one(R0):
            return my_cost(so3jax.simulate(scene, so3jax.RKMK4(), dt=0.01, n_steps=200, R0=R0))

        return float(jnp.mean(jax.vmap(one)(starts)))

    np.testing.assert_allclose(res.initial_cost, mean_cost(4.0, 2.0), rtol=1e-9)
    np.testing.assert_allclose(res.cost, mean_cost(res.gains.k_R, res.gains.k_Omega), rtol=1e-9)
    assert res.cost < res.initial_cost
    assert float(res.gains.k_R) >= 0.1 and float(res.gains.k_Omega) >= 0.1


def test_compare_two_integrators(recipes):
    _, printed = recipes[2]
    rows = re.findall(r"^(\w+)\s+(\d+) steps: error (\S+) rad, (\S+) ms$", printed, re.M)
    assert len(rows) == 6, printed
    for name, order in (("RKMK4", 4), ("CG3", 3)):
        n = np.array([int(r[1]) for r in rows if r[0] == name], float)
        err = np.array([float(r[2]) for r in rows if r[0] == name])
        slope = -np.polyfit(np.log(n), np.log(err), 1)[0]
        assert abs(slope - order) < 0.5, (name, slope)  # errors fall at the method's order
        assert all(float(r[3]) > 0 for r in rows if r[0] == name)


def test_cluster_recipe_uses_the_real_api():
    code, skip = _recipes()[3]
    assert skip and "jax.distributed.initialize()" in code
    args = re.search(r"so3jax\.sweep\((.*?)\n\)", code, re.S).group(1)
    keywords = set(re.findall(r"(\w+)=", args))
    assert keywords <= set(inspect.signature(so3jax.sweep).parameters), keywords
