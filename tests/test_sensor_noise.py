"""Sensor noise on the state a sampled controller reads (`so3jax.SensorNoise`).

The statistics of the perturbation are checked against what was asked for, with the
attitude error recovered by SciPy's rotation vector (not so3jax's ``log``); the control
held at the samples is checked against the controller evaluated on that perturbed state.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import so3jax as s
from so3jax import scenes
from so3jax._quadrotor import _COUNTER, _HELD, DIFFTUNE_INERTIA, DIFFTUNE_MASS
from so3jax._state import LieState

PERIOD, DT, N_STEPS = 0.005, 0.0025, 8  # two steps per hold, four samples after t = 0
STD = {"attitude": (0.01, 0.02, 0.04), "rate": 0.05, "position": 0.1, "velocity": (0.2, 0.1, 0.3)}
N_KEYS = 4000


def _quad(noise=None, control_period=PERIOD):
    base = scenes.quadrotor_circle(control_period=None)
    return scenes.quadrotor(
        DIFFTUNE_MASS,
        DIFFTUNE_INERTIA,
        base.gains,
        base.reference,
        x0=(0.1, -0.2, 0.05),
        v0=(0.3, 0.0, -0.1),
        R0=s.exp(jnp.array([0.2, -0.1, 0.3])),
        Omega0=(0.1, 0.2, -0.3),
        control_period=control_period,
        noise=noise,
    )


def _seed(noise=None, control_period=PERIOD):
    seed = scenes.seed()
    return scenes.tracking(
        seed.body,
        s.GeometricGains(*scenes.SEED_GAINS),
        seed.y0.R[0],
        jnp.array([0.3, -0.2, 0.1]),
        seed.y0.R[1],
        seed.reference,
        control_period=control_period,
        noise=noise,
    )


_simulate = eqx.filter_jit(
    lambda scene: s.simulate(scene, s.RKMK4(), DT, N_STEPS, save_every=2, scalarize=False)
)


def _rotvec(R_true, R_seen):
    """Body-frame tangents ``log(R^T R_seen)`` by SciPy, shape `(N, 3)`."""
    rel = np.einsum("nji,njk->nik", np.asarray(R_true), np.asarray(R_seen))
    return Rotation.from_matrix(rel).as_rotvec()


def _check_std(samples, want, name):
    std = np.std(samples, axis=0)
    want = np.broadcast_to(np.asarray(want, float), (3,))
    assert np.all(np.abs(std / want - 1) < 0.1), (name, std, want)
    # mean zero: within 5 standard errors
    assert np.all(np.abs(np.mean(samples, 0)) < 5 * want / np.sqrt(len(samples))), name


def test_bad_input_names_the_argument():
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="control_period"):
        _quad(s.SensorNoise(rate=0.1, key=key), control_period=None)
    with pytest.raises(ValueError, match="control_period"):
        _seed(s.SensorNoise(rate=0.1, key=key), control_period=None)
    with pytest.raises(ValueError, match="SensorNoise.rate"):
        s.SensorNoise(rate=-0.1, key=key)
    with pytest.raises(ValueError, match="SensorNoise.attitude"):
        s.SensorNoise(attitude=(0.1, -0.1, 0.1), key=key)
    with pytest.raises(ValueError, match="SensorNoise.velocity"):
        s.SensorNoise(velocity=np.ones((2, 3)), key=key)
    with pytest.raises(ValueError, match="SensorNoise.position"):
        s.SensorNoise(position=np.nan, key=key)
    with pytest.raises(ValueError, match="SensorNoise.key"):
        s.SensorNoise(rate=0.1, key="seven")
    with pytest.raises(ValueError, match="position"):  # an attitude scene has no position
        _seed(s.SensorNoise(rate=0.1, position=0.1, key=key))
    with pytest.raises(TypeError, match="noise"):
        _quad(noise=0.1)


def test_quadrotor_perturbation_statistics():
    """Over many keys, the state the controller reads has the standard deviations asked."""
    scene = _quad(s.SensorNoise(**STD, key=jax.random.key(7)))
    y = scene.y0
    t = jnp.asarray(3 * PERIOD)
    keys = jax.random.split(jax.random.key(1), N_KEYS)
    seen = jax.jit(
        jax.vmap(lambda k: eqx.tree_at(lambda sc: sc.noise.key, scene, k).measured(t, y))
    )(keys)
    R = np.broadcast_to(np.asarray(y.R[0]), (N_KEYS, 3, 3))
    _check_std(_rotvec(R, seen.R[:, 0]), STD["attitude"], "attitude")
    for name, sl in (("rate", slice(0, 3)), ("position", slice(3, 6)), ("velocity", slice(6, 9))):
        _check_std(np.asarray(seen.x[:, sl] - y.x[sl]), STD[name], name)
    # the held control and the step counter are not sensed
    np.testing.assert_array_equal(seen.x[:, 9:], np.broadcast_to(y.x[9:], (N_KEYS, y.x.size - 9)))

    # One key, many samples: the draws of different samples are independent and
    # reproducible; a time inside a hold reads the sample it rounds to.
    one = jax.jit(jax.vmap(lambda k: scene.measured(k * PERIOD, y).x[0:3]))
    a = np.asarray(one(jnp.arange(N_KEYS, dtype=float)))
    _check_std(a - y.x[0:3], STD["rate"], "rate over samples")
    assert abs(np.corrcoef(a[1:, 0], a[:-1, 0])[0, 1]) < 0.1
    np.testing.assert_array_equal(a[5], scene.measured(5 * PERIOD + 0.2 * PERIOD, y).x[0:3])


def test_tracking_perturbation_statistics():
    scene = _seed(s.SensorNoise(attitude=0.03, rate=(0.1, 0.2, 0.05), key=3))
    y = scene.y0
    keys = jax.random.split(jax.random.key(2), N_KEYS)
    seen = jax.jit(
        jax.vmap(lambda k: eqx.tree_at(lambda sc: sc.noise.key, scene, k).measured(0.0, y))
    )(keys)
    R = np.broadcast_to(np.asarray(y.R[0]), (N_KEYS, 3, 3))
    _check_std(_rotvec(R, seen.R[:, 0]), 0.03, "attitude")
    _check_std(np.asarray(seen.x[:, :3] - y.x[:3]), (0.1, 0.2, 0.05), "rate")
    # the reference attitude and the held torque are not sensed
    np.testing.assert_array_equal(seen.R[:, 1], np.broadcast_to(y.R[1], (N_KEYS, 3, 3)))
    np.testing.assert_array_equal(seen.x[:, 3:], np.broadcast_to(y.x[3:], (N_KEYS, 4)))


def test_quadrotor_samples_read_the_noisy_state():
    """The first sample (`for_step`) and every later one (`jump`) hold the controller's
    command at the state read; a run under vmap over keys is `test_gust.py`'s."""
    scene = _quad(s.SensorNoise(**STD, key=11)).for_step(DT, 0.0)
    n = int(scene.steps_per_sample)
    t = jnp.asarray(n * DT)
    y = scene.y0
    y = LieState(y.R, y.x.at[_COUNTER].set(n - 1))  # the step before a sample

    def check(scene, t, y):
        held = scene.jump(t, y).x[_HELD]
        seen, true = scene.control(t, scene.measured(t, y)), scene.control(t, y)
        first = scene.control(0.0, scene.measured(0.0, scene.y0))
        return held, jnp.concatenate([seen.f[None], seen.M]), true.M, first, scene.y0.x[_HELD]

    held, want, clean_M, first, held0 = eqx.filter_jit(check)(scene, t, y)
    np.testing.assert_allclose(held, want, rtol=1e-13)
    np.testing.assert_allclose(held0, jnp.concatenate([first.f[None], first.M]), rtol=1e-13)
    assert np.max(np.abs(want[1:] - clean_M)) > 1e-3  # the noise changed the command


def test_tracking_run_reads_noisy_state():
    scene = _seed(s.SensorNoise(attitude=0.05, rate=0.1, key=5))
    tr = _simulate(scene)
    again = _simulate(_seed(s.SensorNoise(attitude=0.05, rate=0.1, key=5)))
    np.testing.assert_array_equal(tr.R, again.R)

    def torque(t, R, Rd, Omega, M):
        y = LieState(jnp.stack([R, Rd]), jnp.concatenate([Omega, M, jnp.zeros(1)]))
        seen = scene.measured(t, y)
        Od, dOd = scene.reference(t)
        return scene.controller(t, scene.body, seen.R[0], seen.x[:3], seen.R[1], Od, dOd, None)

    M = jax.jit(jax.vmap(torque))(tr.t, tr.R, tr.Rd, tr.Omega, tr.M)
    np.testing.assert_allclose(tr.extras["M_cmd"], M, rtol=1e-11, atol=1e-12)


def test_zero_intensity_is_the_noise_free_run():
    zero = s.SensorNoise(key=jax.random.key(4))
    a, b = _simulate(_seed()), _simulate(_seed(zero))
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)
    # The quadrotor drops the zero noise: the scene, hence its run, is the noise-free one.
    plain, dropped = _quad(), _quad(zero)
    assert type(dropped) is type(plain)
    assert jax.tree.structure(dropped) == jax.tree.structure(plain)
    for x, y in zip(jax.tree.leaves(plain), jax.tree.leaves(dropped), strict=True):
        np.testing.assert_array_equal(x, y)
    # Traced zeros draw and add exact zeros: the state read is the true state.
    scene = _quad(s.SensorNoise(**STD, key=1))
    y = scene.y0
    zeroed = jax.jit(
        lambda sd: eqx.tree_at(
            lambda sc: (sc.noise.attitude, sc.noise.rate, sc.noise.position, sc.noise.velocity),
            scene,
            (sd, sd, sd, sd),
        ).measured(0.0, y)
    )(jnp.zeros(3))
    np.testing.assert_array_equal(zeroed.R, y.R)
    np.testing.assert_array_equal(zeroed.x, y.x)


def test_no_noise_leaves_the_program_unchanged():
    """``noise=None`` builds the scene classes without noise, and no draw in the program."""

    def jaxpr(scene):
        sim = lambda sc: s.simulate(sc, s.RKMK4(), DT, 2, scalarize=False)  # noqa: E731
        return str(jax.make_jaxpr(sim)(scene))

    plain = _quad()
    assert type(plain) is scenes.Quadrotor and type(_seed()) is scenes.SampledTracking
    assert "random" not in jaxpr(plain) and "threefry" not in jaxpr(plain)
    program = jaxpr(_seed())
    assert program == jaxpr(_seed(s.SensorNoise(key=3)))
    assert "random" not in program and "threefry" not in program
    assert "random" in jaxpr(_seed(s.SensorNoise(rate=0.1, key=3)))


def test_threefry_is_jax_s_own():
    """The draws' hash is Threefry-2x32 as JAX computes it (`jax.extend.random`)."""
    from jax.extend.random import threefry_2x32

    from so3jax._sensors import threefry2x32

    key = jnp.array([123, 456789], jnp.uint32)
    count = jnp.arange(8, dtype=jnp.uint32) * 977
    a, b = threefry2x32(key[0], key[1], count[:4], count[4:])
    np.testing.assert_array_equal(jnp.concatenate([a, b]), threefry_2x32(key, count))


def test_noisy_batch_is_scalarized_and_float32_stays_float32():
    """A batch of noisy runs takes the scalarized program (the draws are integer
    arithmetic) and equals the array program's runs; float32 runs stay float32."""
    noise = s.SensorNoise(attitude=0.02, rate=0.05, key=0)
    sc = _seed(noise)
    keys = jax.random.split(jax.random.key(5), 16)  # the scalarized layout's threshold

    def run(k, scalarize=None):
        one = eqx.tree_at(lambda q: q.noise.key, sc, k)
        return s.simulate(one, s.LieEuler(), DT, N_STEPS, scalarize=scalarize).Omega

    plan = s.explain(jax.vmap(run), keys)
    assert [e["layout"] for e in plan.of("layout")] == ["scalarized"], plan
    fast = jax.jit(jax.vmap(run))(keys)
    plain = jax.jit(jax.vmap(lambda k: run(k, False)))(keys)
    assert np.abs(np.asarray(fast - plain)).max() < 1e-12 * np.abs(np.asarray(plain)).max()
    seed32 = scenes.seed(dtype=jnp.float32)
    sc32 = scenes.tracking(
        seed32.body, s.GeometricGains(*scenes.SEED_GAINS), seed32.y0.R[0],
        jnp.zeros(3, jnp.float32), seed32.y0.R[1], seed32.reference,
        control_period=PERIOD, noise=noise,
    )  # fmt: skip
    tr = s.simulate(sc32, s.LieEuler(), DT, N_STEPS)
    assert tr.R.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(tr.Omega)))


def test_normals_are_the_inverse_normal_cdf_of_their_words():
    """Each 32-bit word's top 24 bits ``m`` give the normal ``sqrt(2) erfinv(2 u - 1)``,
    ``u = (m + 1/2) / 2^24``: to 2e-7 relative (Giles' approximation) against SciPy,
    over the whole range, the extreme words (about 5.4 sigma) included."""
    from scipy.special import erfinv

    from so3jax._sensors import _gaussian

    m = np.concatenate([np.arange(0, 2**24, 4099), [0, 1, 2**23 - 1, 2**23, 2**24 - 1]])
    words = jnp.asarray((m.astype(np.uint32) << 8) | 0x5A, jnp.uint32)  # low bits ignored
    want = np.sqrt(2.0) * erfinv(2.0 * (m + 0.5) / 2**24 - 1.0)
    got = np.asarray(_gaussian(words, jnp.float64))
    assert np.max(np.abs(got - want) / np.abs(want)) < 2e-7
    assert np.max(np.abs(want)) > 5.3
    got32 = np.asarray(_gaussian(words, jnp.float32))
    assert got32.dtype == np.float32 and np.max(np.abs(got32 - want) / np.abs(want)) < 2e-6
