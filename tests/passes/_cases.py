"""The runs every pass of the engine is proved on, and the reference they are compared with.

Five steps (the seed's Lie-Euler step, its LGVI step, the quadrotor with its control held
over a period, a step containing ``lax.cond``, and the free body's Lie-Euler step), each
as a function of two differentiated scalars ``k``, under five transforms: ``jit`` of one
run's trajectory, ``vmap`` of a batch (its mean cost), and ``grad``, ``jacfwd`` and
``jax.hessian`` of that mean (first derivatives only for `FIRST_ORDER`). The reference
is the same call with every pass off (`so3jax._engine.policy.using(passes=frozenset())`): the
array program, batched and differentiated by the engine's derivative strategies, which
``tests/test_engine.py`` proves equal to JAX's own autodiff. Each case is built in float64
or float32 (scene, starts and ``k``), and the results must stay in that dtype (`RTOL`).

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
import pytest

import so3jax as s
from so3jax._engine import policy, run
from so3jax._tune import with_gains

#: The steps the passes are proved on; the first four are the issue's, together by default.
CASES = ("seed", "lgvi", "quadrotor", "cond", "free")
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


def _starts(key, n, dtype):
    return s.initial_states(jax.random.key(key), n, dtype=dtype)


def _attitude(method, dtype):
    """The seed (tracking a moving reference) stepped by ``method``."""
    scene = s.scenes.seed(dtype=dtype)
    R0s, W0s = _starts(1, B, dtype)
    w = jnp.linspace(0.5, 1.5, 9, dtype=dtype).reshape(3, 3)

    def one(k, R0, W0):
        tr = s.simulate(with_gains(scene, k[0], k[1]), method, 0.01, N, SAVE, R0=R0, Omega0=W0)
        return jnp.sum(tr.R * w) + jnp.sum(tr.Omega**2) * 0.1

    def trajectory(k):
        tr = s.simulate(with_gains(scene, k[0], k[1]), method, 0.01, N, SAVE)
        return tr.R, tr.Omega

    return one, trajectory, (R0s, W0s)


def _quadrotor(dtype):
    """The quadrotor of Lee et al. on DiffTune's circle, its control held over each step;
    ``k`` scales the attitude and rate gains."""
    dt = 0.0025
    scene = s.scenes.quadrotor_circle(control_period=dt, dtype=dtype)
    R0s, _ = _starts(2, B, dtype)
    R0s = jax.vmap(lambda R: s.exp(0.3 * s.log(R)))(R0s)  # tilted starts

    def scaled(k):
        g = scene.gains
        return eqx.tree_at(
            lambda sc: (sc.gains.k_R, sc.gains.k_Omega), scene, (k[0] * g.k_R, k[1] * g.k_Omega)
        )

    def one(k, R0, _):
        tr = s.simulate(scaled(k / K0.astype(dtype)), s.LieEuler(), dt, N, SAVE, R0=R0)
        return jnp.sum(tr.extras["e_x"] ** 2) + jnp.sum(tr.R[..., 2, :])

    def trajectory(k):
        tr = s.simulate(scaled(k / K0.astype(dtype)), s.LieEuler(), dt, N, SAVE)
        return tr.R, tr.Omega

    return one, trajectory, (R0s, R0s)


def _cond(dtype):
    """A toy loop whose step branches with ``lax.cond`` on its state."""
    W = jnp.array([1.0, -0.5, 0.25], dtype)

    def step(P, c):
        x, i = c
        grow = lambda x: x + 0.1 * jnp.sin(P[0] * x * W) + 0.01 * P[1] ** 2
        shrink = lambda x: 0.9 * x - 0.05 * jnp.cos(P[1] * x)
        return jax.lax.cond(jnp.sum(x) > 0.2, grow, shrink, x), i + 1

    def observe(P, c):
        return jnp.sum(W * c[0] ** 2), c[0]

    def go(k, x0):
        return run(step, observe, k, (x0, jnp.array(0, jnp.int32)), N, SAVE)[0]

    x0s = jnp.array([[0.1, 0.4, -0.3], [0.3, -0.2, 0.5], [-0.4, 0.1, 0.2], [0.2, 0.2, 0.2]], dtype)

    def one(k, x0, _):
        return jnp.sum(go(k, x0)[0])

    def trajectory(k):
        return go(k, x0s[0])

    return one, trajectory, (x0s, x0s)


def _free(dtype):
    """The torque-free body (Dzhanibekov's inertia), ``k`` scaling its initial rates."""
    J = jnp.array([1.0, 2.0, 3.0], dtype)
    R0s, _ = _starts(3, B, dtype)
    W0s = jnp.array([[0.1, 2.0, 0.05], [1.0, 0.2, 0.3], [0.3, 0.3, 1.5], [0.5, -1.0, 0.2]], dtype)
    w = jnp.linspace(0.5, 1.5, 9, dtype=dtype).reshape(3, 3)

    def simulate(k, R0, W0):
        scene = s.scenes.free_body(J, R0, W0 * jnp.stack([k[0], k[1], k[0]]))
        return s.simulate(scene, s.LieEuler(), 0.05, N, SAVE)

    def one(k, R0, W0):
        tr = simulate(k, R0, W0)
        return jnp.sum(tr.R * w) + jnp.sum(tr.Omega**2) * 0.1

    def trajectory(k):
        tr = simulate(k, R0s[0], W0s[0])
        return tr.R, tr.Omega

    return one, trajectory, (R0s, W0s)


def _case(name, dtype):
    if name == "seed":
        return _attitude(s.LieEuler(), dtype)
    if name == "lgvi":
        return _attitude(s.LGVI(), dtype)
    if name == "quadrotor":
        return _quadrotor(dtype)
    if name == "free":
        return _free(dtype)
    return _cond(dtype)


def functions(name, dtype="float64") -> dict:
    """The five transforms of case ``name`` in ``dtype``, each a function of ``k``."""
    one, trajectory, starts = _case(name, dtype)

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


def results(name, passes, dtype="float64") -> dict:
    """Every transform of case ``name`` in ``dtype`` under `SMALL` with ``passes`` on."""
    with policy.using(SMALL, passes=frozenset(passes)):
        out = {t: f(K0.astype(dtype)) for t, f in functions(name, dtype).items()}
        return jax.tree.map(np.asarray, out)


@functools.cache
def cached(name, passes: frozenset, dtype="float64") -> dict:
    """`results`, computed once per process."""
    return results(name, passes, dtype)


def reference(name, dtype="float64") -> dict:
    """`results` with every pass off."""
    return cached(name, frozenset(), dtype)


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
#: alone on the step with ``lax.cond`` (`alone` names the exception), all together on the
#: first four cases. (Any of `CASES`, comma separated: ``SO3JAX_TEST_PASS_CASES=seed,cond``
#: proves each pass alone on the seed too.)
ALONE = _cases_from("SO3JAX_TEST_PASS_CASES", "cond")
TOGETHER = _cases_from("SO3JAX_TEST_PASS_TOGETHER", ",".join(CASES[:4]))


def alone(pass_name: str) -> tuple:
    """The cases pass ``pass_name`` is proved alone on: `ALONE`, less those it leaves
    unchanged (`assert_acts`): ``frames`` acts on attitude tangents, which the ``lax.cond``
    step has none of, so it is proved on the free body's step (``"free"``) instead."""
    if pass_name == "frames":
        return tuple(c for c in ALONE if c != "cond") or ("free",)
    return ALONE


@functools.cache
def programs(name, passes: frozenset) -> dict:
    """The printed jaxpr of every transform of case ``name`` under `SMALL` with ``passes``
    on (traced, not run)."""
    with policy.using(SMALL, passes=passes):
        fns = functions(name)
        return {t: str(jax.make_jaxpr(f)(K0)) for t, f in fns.items()}


#: Passes the policy applies on one CPU device only (`so3jax._engine.policy.one_cpu_device`):
#: elsewhere they leave every program as it is, and only their equality is proved.
ONE_CPU_DEVICE_ONLY = frozenset({"hoist", "cuts", "tiles"})

#: A test of what such a pass does, skipped elsewhere.
ON_ONE_CPU_DEVICE = pytest.mark.skipif(
    not policy.one_cpu_device(), reason="the pass acts on one CPU device only"
)


def assert_acts(pass_name: str, name: str) -> None:
    """Pass ``pass_name`` changes the program of at least one transform of case ``name``
    (against what it needs alone, `NEEDS`), so that the comparison with the reference is
    not of a program with itself."""
    if pass_name in ONE_CPU_DEVICE_ONLY and not policy.one_cpu_device():
        pytest.skip(f"the {pass_name!r} pass acts on one CPU device only")
    needs = frozenset(NEEDS[pass_name])
    on, off = programs(name, needs | {pass_name}), programs(name, needs)
    changed = [t for t in on if on[t] != off[t]]
    assert changed, (pass_name, name, "the pass changes no transform's program")


def plan(name, transform, passes):
    """`so3jax.explain` of one transform of case ``name`` with ``passes`` on."""
    fn = functions(name)[transform]
    with policy.using(SMALL, passes=frozenset(passes)):
        return s.explain(getattr(fn, "__wrapped__", fn), K0)


#: How closely a program with passes on equals the reference, relative to each result's
#: largest entry: the passes reorder floating-point operations (terms written out,
#: components instead of arrays, three-number tangents), so the two agree to round-off
#: accumulated over the run and its derivatives, not bit for bit.
RTOL = {"float64": 1e-12, "float32": 1e-5}

#: The dtypes each pass is proved in: float32 on the steps of `ALONE` (each pass alone and
#: all together); float64 on every case.
DTYPES = tuple(RTOL)


def assert_equal_to_reference(passes, name, dtype="float64"):
    """Every transform of case ``name`` in ``dtype`` with ``passes`` on equals the
    reference to `RTOL` (relative to each result's largest entry), and stays in ``dtype``."""
    got = cached(name, frozenset(passes), dtype)
    ref = reference(name, dtype)
    assert got.keys() == ref.keys()
    for t in got:
        for a, b in zip(jax.tree.leaves(got[t]), jax.tree.leaves(ref[t]), strict=True):
            assert a.dtype == b.dtype, (sorted(passes), name, t, a.dtype, b.dtype)
            if np.issubdtype(b.dtype, np.floating):
                assert b.dtype == np.dtype(dtype), (name, t, b.dtype)
            scale = max(float(np.max(np.abs(b))), 1e-300)
            err = float(np.max(np.abs(a - b))) / scale
            assert err < RTOL[dtype], (sorted(passes), name, t, dtype, err)


def assert_alone_equals_reference(pass_name: str, name: str, dtype="float64") -> None:
    """Pass ``pass_name`` alone (with what it needs, `NEEDS`) equals the reference on case
    ``name`` in ``dtype`` under ``jit``, ``vmap``, ``grad``, ``jacfwd`` and ``jax.hessian``
    (`assert_equal_to_reference`), and changes what it is compared on (`assert_acts`), so
    the comparison is not of a program with itself.

    Each ``test_pass_<name>.py`` runs it on the steps of `alone`, in every dtype of
    `DTYPES`; ``test_passes_together.py`` runs every pass together on those of `TOGETHER`."""
    assert_equal_to_reference(NEEDS[pass_name] | {pass_name}, name, dtype)
    assert_acts(pass_name, name)
