"""Gusts (`so3jax.Gust`): a stationary Ornstein–Uhlenbeck wind per axis.

The statistics over many keys are compared with the process's own law (mean ``mu``,
standard deviation ``sigma``, autocorrelation ``exp(-|s| / T)``), independent of how
the path is drawn.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import so3jax as s
from so3jax import scenes
from so3jax._quadrotor import DIFFTUNE_GAINS, DIFFTUNE_INERTIA, DIFFTUNE_MASS

MU = np.array([1.0, -2.0, 0.5])
SIGMA = np.array([0.5, 1.0, 2.0])
TAU = np.array([0.2, 0.5, 1.0])
N_KEYS = 4000


@pytest.fixture(scope="module")
def batch():
    """``N_KEYS`` independent gusts over 3 s, and a function of them evaluated at times."""
    keys = jax.random.split(jax.random.key(0), N_KEYS)
    gusts = jax.jit(jax.vmap(lambda k: s.Gust(MU, SIGMA, TAU, duration=3.0, key=k)))(keys)
    at = jax.jit(jax.vmap(lambda g, t: jax.vmap(g)(t), in_axes=(0, None)))
    return gusts, lambda t: np.asarray(at(gusts, jnp.asarray(t)))


def test_stationary_mean_and_std(batch):
    _, at = batch
    # grid points and points between them, at the start, in the middle and near the end
    w = at([0.0, 0.005, 0.503, 1.0, 1.7371, 2.99])  # (N, 6, 3)
    for j in range(w.shape[1]):
        mean, std = w[:, j].mean(0), w[:, j].std(0)
        assert np.all(np.abs(mean - MU) < 0.1 * SIGMA), (j, mean)
        assert np.all(np.abs(std / SIGMA - 1) < 0.1), (j, std)


def test_autocorrelation_at_one_correlation_time(batch):
    _, at = batch
    starts = np.array([0.0, 0.45, 0.9])  # + 2 T stays inside the 3 s
    for i in range(3):
        w = at(np.concatenate([starts, starts + TAU[i]]))[:, :, i]
        rho = [np.corrcoef(w[:, j], w[:, j + 3])[0, 1] for j in range(3)]
        assert abs(np.mean(rho) - math.exp(-1)) < 0.04, (i, rho)
        # and at two correlation times, exp(-2)
        w2 = at(starts + 2 * TAU[i])[:, :, i]
        rho2 = [np.corrcoef(w[:, j], w2[:, j])[0, 1] for j in range(3)]
        assert abs(np.mean(rho2) - math.exp(-2)) < 0.05, (i, rho2)


def test_exact_update_on_a_coarse_grid():
    """The update is the exact one: at grid points ``h = T / 2`` apart, the correlation at
    lag ``T`` is still ``exp(-1)`` (an Euler step would give ``(1 - 1/2)^2 = 0.25``)."""
    keys = jax.random.split(jax.random.key(1), N_KEYS)
    paths = jax.jit(jax.vmap(lambda k: s.Gust(0.0, 1.0, 0.4, duration=2.0, key=k, step=0.2).path))(
        keys
    )
    p = np.asarray(paths)  # (N, 11, 3), t = 0, 0.2, ..., 2.0
    assert p.shape == (N_KEYS, 11, 3)
    rho = np.mean(
        [np.corrcoef(p[:, j, a], p[:, j + 2, a])[0, 1] for j in (0, 4, 8) for a in range(3)]
    )
    assert abs(rho - math.exp(-1)) < 0.03
    assert np.all(np.abs(p.std(0) - 1) < 0.1)


def test_reproducible_interpolated_and_differentiable():
    g = s.Gust(MU, SIGMA, TAU, duration=1.0, key=jax.random.key(3))
    again = s.Gust(MU, SIGMA, TAU, duration=1.0, key=jax.random.key(3))
    other = s.Gust(MU, SIGMA, TAU, duration=1.0, key=jax.random.key(4))
    np.testing.assert_array_equal(g.path, again.path)
    assert not np.array_equal(g.path, other.path)
    assert g.path.shape == (101, 3)  # h = min(T) / 20 = 0.01 over 1 s
    h = float(g.step)
    z = np.asarray(g.path)
    # grid values, linear in between, held outside the grid
    np.testing.assert_allclose(g(7 * h), MU + SIGMA * z[7], rtol=1e-12)
    np.testing.assert_allclose(g(7.25 * h), MU + SIGMA * (0.75 * z[7] + 0.25 * z[8]), rtol=1e-12)
    np.testing.assert_allclose(g(-1.0), MU + SIGMA * z[0], rtol=1e-12)
    np.testing.assert_allclose(g(5.0), MU + SIGMA * z[-1], rtol=1e-12)
    # d/dt inside a segment: the slope, and central differences
    t = 0.4237
    dw = jax.jacfwd(g)(jnp.asarray(t))
    i = int(t / h)
    np.testing.assert_allclose(dw, SIGMA * (z[i + 1] - z[i]) / h, rtol=1e-9)
    eps = 1e-6
    np.testing.assert_allclose(dw, (g(t + eps) - g(t - eps)) / (2 * eps), rtol=1e-6)
    # gradients in the mean and the intensity
    dmu = jax.grad(lambda gg: gg(t)[1])(g).mean
    np.testing.assert_allclose(dmu, [0.0, 1.0, 0.0])
    # a float32 gust
    g32 = s.Gust(MU, SIGMA, TAU, duration=1.0, key=3, dtype=jnp.float32)
    assert g32.path.dtype == jnp.float32 and g32(0.5).dtype == jnp.float32


def test_bad_input_names_the_argument():
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="intensity"):
        s.Gust(0.0, -1.0, 1.0, duration=1.0, key=key)
    with pytest.raises(ValueError, match="correlation_time"):
        s.Gust(0.0, 1.0, (1.0, 0.0, 1.0), duration=1.0, key=key)
    with pytest.raises(ValueError, match="mean"):
        s.Gust((1.0, 2.0), 1.0, 1.0, duration=1.0, key=key)
    with pytest.raises(ValueError, match="duration"):
        s.Gust(0.0, 1.0, 1.0, duration=0.0, key=key)
    with pytest.raises(ValueError, match="step"):
        s.Gust(0.0, 1.0, 1.0, duration=1.0, key=key, step=-0.1)


def test_quadrotor_in_a_gust_under_jit_and_vmap():
    """A hovering quadrotor with drag in a gust blowing along +e1, reading noisy sensors
    (`SensorNoise`): one gust and one noise sequence per key."""
    k_x, k_v, k_R, k_O = DIFFTUNE_GAINS
    scene = scenes.quadrotor(
        DIFFTUNE_MASS,
        DIFFTUNE_INERTIA,
        s.QuadrotorGains(k_x, k_v, k_R, k_O),
        s.HoverReference(),
        control_period=0.005,
        drag=0.5,
        wind=s.Gust((3.0, 0.0, 0.0), 0.5, 0.5, duration=0.1, key=0),
        noise=s.SensorNoise(0.002, 0.01, 0.005, 0.01, key=0),
    )

    def run(key):
        gust = s.Gust((3.0, 0.0, 0.0), 0.5, 0.5, duration=0.1, key=key)
        noise_key = jax.random.fold_in(key, 1)
        sc = eqx.tree_at(lambda sc: (sc.wind, sc.noise.key), scene, (gust, noise_key))
        return s.simulate(sc, s.RKMK4(), 0.0025, 16, 4, scalarize=False)

    keys = jnp.stack([jax.random.key(1), jax.random.key(1), jax.random.key(2)])
    tr = jax.jit(jax.vmap(run))(keys)
    assert np.all(np.asarray(tr.status.code) == 0)
    np.testing.assert_array_equal(tr.extras["v"][0], tr.extras["v"][1])
    assert not np.array_equal(tr.extras["v"][0], tr.extras["v"][2])
    # pushed downwind at first: m v' ~ d (w - v) along e1 while the controller catches up
    v = np.asarray(tr.extras["v"])[:, -1]
    assert np.all(v[:, 0] > 0)
