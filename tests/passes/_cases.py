"""The runs every pass of the engine is proved on, and the reference they are compared with.

Four steps (the seed's Lie-Euler step, its LGVI step, the quadrotor with its control held
over a period, and a step containing ``lax.cond``), each as a function of two
differentiated scalars ``k``,
under five transforms: ``jit`` of one run's trajectory, ``vmap`` of a batch (its mean
cost), and ``grad``, ``jacfwd`` and ``jax.hessian`` of that mean (first derivatives only
for `FIRST_ORDER`). The reference is the
same call with every pass off (`so3jax._engine.policy.using(passes=frozenset())`): the
array program, batched and differentiated by the engine's derivative strategies, which
``tests/test_engine.py`` proves equal to JAX's own autodiff.

The policy the passes run under (`SMALL`) lowers the batch thresholds, so that a batch of
four runs is scalarized, cut, tiled and hoisted as a large one would be: the passes act
on the programs these tests compile, and the plan (`so3jax.explain`) says so.
"""

from __future__ import annotations

import functools
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import so3jax as s
from so3jax._engine import policy, run
from so3jax._tune import with_gains

CASES = ("seed", "lgvi", "quadrotor", "cond")
TRANSFORMS = ("jit", "vmap", "grad", "jacfwd", "hessian")
B, N, SAVE = 4, 6, 2
K0 = jnp.array([3.0, 1.5])

#: The passes each pass needs to act at all (its module says why).
NEEDS = {
    "scalarize": set(),
    "cuts": {"scalarize"},
    "frames": {"scalarize"},
    "hoist": set(),
    "unroll": {"hoist"},
    "tiles": {"scalarize"},
    "settle": set(),
}

#: Thresholds low enough for a batch of `B` runs with two tangent columns to take every
#: pass: scalarized and cut from 2 runs, tiles of 2 runs, column cuts from 2.
SMALL = policy.DEFAULT.replace(
    batched_layout={
        "run": (2, 2),
        "scalar": (1, 2),
        "jacobian": (2, 2),
        "array": (None, None),
        "jvp": (None, None),  # second derivatives: scalarized in tests/test_engine.py
    },
    gpu_layout={},
    tile_values=6,
    tile_multiple=1,
    tile_max_observed=64,
    column_cuts_from=2,
)


def _starts(key, n):
    return s.initial_states(jax.random.key(key), n)


def _attitude(method):
    """The seed (tracking a moving reference) stepped by ``method``."""
    scene = s.scenes.seed()
    R0s, W0s = _starts(1, B)
    w = jnp.linspace(0.5, 1.5, 9).reshape(3, 3)

    def one(k, R0, W0):
        tr = s.simulate(with_gains(scene, k[0], k[1]), method, 0.01, N, SAVE, R0=R0, Omega0=W0)
        return jnp.sum(tr.R * w) + jnp.sum(tr.Omega**2) * 0.1

    def trajectory(k):
        tr = s.simulate(with_gains(scene, k[0], k[1]), method, 0.01, N, SAVE)
        return tr.R, tr.Omega

    return one, trajectory, (R0s, W0s)


def _quadrotor():
    """The quadrotor of Lee et al. on DiffTune's circle, its control held over each step;
    ``k`` scales the attitude and rate gains."""
    dt = 0.0025
    scene = s.scenes.quadrotor_circle(control_period=dt)
    R0s, _ = _starts(2, B)
    R0s = jax.vmap(lambda R: s.exp(0.3 * s.log(R)))(R0s)  # tilted starts

    def scaled(k):
        g = scene.gains
        return eqx.tree_at(
            lambda sc: (sc.gains.k_R, sc.gains.k_Omega), scene, (k[0] * g.k_R, k[1] * g.k_Omega)
        )

    def one(k, R0, _):
        tr = s.simulate(scaled(k / K0), s.LieEuler(), dt, N, SAVE, R0=R0)
        return jnp.sum(tr.extras["e_x"] ** 2) + jnp.sum(tr.R[..., 2, :])

    def trajectory(k):
        tr = s.simulate(scaled(k / K0), s.LieEuler(), dt, N, SAVE)
        return tr.R, tr.Omega

    return one, trajectory, (R0s, R0s)


def _cond():
    """A toy loop whose step branches with ``lax.cond`` on its state."""
    W = jnp.array([1.0, -0.5, 0.25])

    def step(P, c):
        x, i = c
        grow = lambda x: x + 0.1 * jnp.sin(P[0] * x * W) + 0.01 * P[1] ** 2
        shrink = lambda x: 0.9 * x - 0.05 * jnp.cos(P[1] * x)
        return jax.lax.cond(jnp.sum(x) > 0.2, grow, shrink, x), i + 1

    def observe(P, c):
        return jnp.sum(W * c[0] ** 2), c[0]

    def go(k, x0):
        return run(step, observe, k, (x0, jnp.array(0, jnp.int32)), N, SAVE)[0]

    x0s = jnp.array([[0.1, 0.4, -0.3], [0.3, -0.2, 0.5], [-0.4, 0.1, 0.2], [0.2, 0.2, 0.2]])

    def one(k, x0, _):
        return jnp.sum(go(k, x0)[0])

    def trajectory(k):
        return go(k, x0s[0])

    return one, trajectory, (x0s, x0s)


def _case(name):
    if name == "seed":
        return _attitude(s.LieEuler())
    if name == "lgvi":
        return _attitude(s.LGVI())
    if name == "quadrotor":
        return _quadrotor()
    return _cond()


def functions(name) -> dict:
    """The five transforms of case ``name``, each a function of ``k``."""
    one, trajectory, starts = _case(name)

    def mean(k):
        return jnp.mean(jax.vmap(lambda a, b: one(k, a, b))(*starts))

    fns = {
        "jit": jax.jit(trajectory),
        "vmap": jax.jit(mean),
        "grad": jax.jit(jax.grad(mean)),
        "jacfwd": jax.jit(jax.jacfwd(mean)),
        "hessian": jax.jit(jax.hessian(mean)),
    }
    if name in FIRST_ORDER:
        del fns["hessian"]
    return fns


def results(name, passes) -> dict:
    """Every transform of case ``name`` under `SMALL` with ``passes`` on."""
    with policy.using(SMALL, passes=frozenset(passes)):
        out = {t: f(K0) for t, f in functions(name).items()}
        return jax.tree.map(np.asarray, out)


@functools.cache
def cached(name, passes: frozenset) -> dict:
    """`results`, computed once per process."""
    return results(name, passes)


def reference(name) -> dict:
    """`results` with every pass off."""
    return cached(name, frozenset())


#: Cases whose second derivatives are not compiled in the suite: a Hessian of LGVI's or
#: the quadrotor's batch compiles for 10 to 30 s under each policy, and for minutes with
#: XLA's default flags (the seed's and the ``lax.cond`` step's prove the passes under
#: ``jax.hessian``). ``SO3JAX_TEST_SECOND_ORDER`` names those compiled too (``all``, or
#: cases comma separated): CI's newest-JAX step (``.ci/run``) adds LGVI's.
_SECOND = os.environ.get("SO3JAX_TEST_SECOND_ORDER", "")
FIRST_ORDER = tuple(
    c for c in ("lgvi", "quadrotor") if _SECOND != "all" and c not in _SECOND.split(",")
)


def _cases_from(variable: str, default: str) -> tuple:
    return tuple(c for c in os.environ.get(variable, default).split(",") if c in CASES)


#: The cases each pass module proves its pass alone on (``SO3JAX_TEST_PASS_CASES``), and
#: those ``test_passes_together.py`` proves every pass together on
#: (``SO3JAX_TEST_PASS_TOGETHER``). Compiling one case's transforms under one policy takes
#: seconds, and seven policies over four cases would double the suite's time: each pass
#: alone on the step with ``lax.cond``, all together on every case. (Any of `CASES`, comma
#: separated: ``SO3JAX_TEST_PASS_CASES=seed,cond`` proves each pass alone on the seed too.)
ALONE = _cases_from("SO3JAX_TEST_PASS_CASES", "cond")
TOGETHER = _cases_from("SO3JAX_TEST_PASS_TOGETHER", ",".join(CASES))


def plan(name, transform, passes):
    """`so3jax.explain` of one transform of case ``name`` with ``passes`` on."""
    fn = functions(name)[transform]
    with policy.using(SMALL, passes=frozenset(passes)):
        return s.explain(getattr(fn, "__wrapped__", fn), K0)


def assert_equal_to_reference(passes, name, rtol=1e-10):
    """Every transform of case ``name`` with ``passes`` on equals the reference to ``rtol``
    (relative to each result's largest entry)."""
    got = cached(name, frozenset(passes))
    ref = reference(name)
    assert got.keys() == ref.keys()
    for t in got:
        for a, b in zip(jax.tree.leaves(got[t]), jax.tree.leaves(ref[t]), strict=True):
            scale = max(float(np.max(np.abs(b))), 1e-300)
            err = float(np.max(np.abs(a - b))) / scale
            assert err < rtol, (sorted(passes), name, t, err)
