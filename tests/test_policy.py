"""The engine's policy (`so3jax._engine.policy`): one frozen object, read at trace time."""

import warnings

import jax
import pytest

import so3jax as s
from so3jax._engine import policy


def test_policy_is_frozen_hashable_and_checks_its_passes():
    p = policy.DEFAULT
    with pytest.raises(AttributeError):
        p.tile_values = 1  # frozen
    assert hash(p.replace(batched_layout={"run": (1, 1)})) != hash(p)  # tables hash too
    assert p.replace(batched_layout={"run": (1, 1)}).batched_layout == (("run", (1, 1)),)
    with pytest.raises(ValueError, match="passes: unknown"):
        policy.Policy(passes=frozenset({"scalarize", "warp"}))


def test_using_nests_and_restores():
    before = policy.current()
    with policy.using(passes=frozenset()) as off:
        assert policy.current() is off and not off.passes
        with policy.using(tile_values=12) as inner:
            assert inner.tile_values == 12 and not inner.passes  # changes on the active one
        assert policy.current() is off
    assert policy.current() is before
    # with the scalarize pass off no program is scalarized, whatever the table says
    with policy.using(passes=policy.PASSES - {"scalarize"}):
        assert policy.batched_layout("run") == (None, None)
    with policy.using(passes=policy.PASSES - {"cuts"}):
        assert policy.batched_layout("run")[1] is None


@pytest.mark.parametrize(
    "env, want",
    [
        ({}, policy.PASSES),
        ({"SO3JAX_PASSES": "none"}, set()),
        ({"SO3JAX_PASSES": "scalarize, hoist"}, {"scalarize", "hoist"}),
        ({"SO3JAX_FRAME_TANGENTS": "0"}, policy.PASSES - {"frames"}),
        ({"SO3JAX_HOIST_LOOPS": "0"}, policy.PASSES - {"hoist"}),
    ],
)
def test_default_from_the_environment(monkeypatch, env, want):
    for name in ("SO3JAX_PASSES", "SO3JAX_FRAME_TANGENTS", "SO3JAX_HOIST_LOOPS"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("SO3JAX_HOIST_LOOPS", "1")  # (whatever this jaxlib is)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    assert policy._from_env().passes == frozenset(want)


def test_unknown_pass_in_the_environment_warns(monkeypatch):
    monkeypatch.setenv("SO3JAX_PASSES", "hoist,warp")
    monkeypatch.setenv("SO3JAX_HOIST_LOOPS", "1")
    with pytest.warns(UserWarning, match="warp"):
        assert policy._from_env().passes == {"hoist"}
    monkeypatch.setenv("SO3JAX_PASSES", "all")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        policy._from_env()


def test_a_changed_policy_takes_effect_on_new_traces():
    """A batch traced under the default policy and, after `jax.clear_caches` (JAX caches
    batched programs without knowing the policy), with every pass off gives two programs
    (the scalarized and the array one), and the default again the first; the values
    agree."""
    scene = s.scenes.seed()
    R0s = s.random_rotation(jax.random.key(0), (16,))

    def batch(R0s):
        return jax.vmap(lambda R0: s.simulate(scene, s.LieEuler(), 0.01, 4, 2, R0=R0).R)(R0s)

    first = str(jax.make_jaxpr(batch)(R0s))
    jax.clear_caches()
    with policy.using(passes=frozenset()):
        off = str(jax.make_jaxpr(batch)(R0s))
        plain = batch(R0s)
    jax.clear_caches()
    assert off != first
    assert str(jax.make_jaxpr(batch)(R0s)) == first
    assert float(abs(batch(R0s) - plain).max()) < 1e-12


def test_a_new_function_sees_a_changed_policy_without_clearing_caches():
    """so3jax's entry points key their programs by the policy: a function traced anew under
    another policy takes that policy's plan (a batch, and the gradient of its mean), with no
    `jax.clear_caches`; a function already traced keeps its trace, as documented."""
    import jax.numpy as jnp

    from so3jax._tune import with_gains

    scene = s.scenes.seed()
    R0s = s.random_rotation(jax.random.key(1), (16,))

    def fresh():
        def batch(k):
            sc = with_gains(scene, k, 2.0)
            return jax.vmap(lambda R0: s.simulate(sc, s.LieEuler(), 0.01, 4, 2, R0=R0).R)(R0s)

        return batch

    def layouts(fn, *args):
        return sorted({e["layout"] for e in s.explain(fn, *args).of("layout")})

    def traced(fn, *args):
        return str(jax.make_jaxpr(fn)(*args))

    mean_grad = lambda f: jax.grad(lambda k: jnp.mean(f(k)[..., 0, 0]))  # noqa: E731
    kept = fresh()
    on = {"batch": traced(kept, 3.0), "grad": traced(mean_grad(fresh()), 3.0)}
    assert layouts(fresh(), 3.0) == ["scalarized"]
    with policy.using(passes=frozenset()):
        assert layouts(fresh(), 3.0) == ["array"]
        assert traced(fresh(), 3.0) != on["batch"]
        assert traced(mean_grad(fresh()), 3.0) != on["grad"]
        assert traced(kept, 3.0) == on["batch"]  # JAX's trace of a function it has seen
    assert traced(fresh(), 3.0) == on["batch"]
