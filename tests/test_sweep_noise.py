"""Sensor noise in sweeps: one noise key per run, and the ``noise_scale`` parameter.

Each run of a sweep is checked against a scene built by the public constructors
(`scenes.tracking(..., noise=SensorNoise(c sigma, key=k))`, `scenes.quadrotor`) and run
by `simulate`, with the key computed here from the rule `sweep` documents,
``fold_in(fold_in(key, a), 2**31 - 1)`` for the runs from attitude ``a``.
"""

import matplotlib

matplotlib.use("Agg")

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import so3jax as s
from so3jax import _sweep, plot, scenes
from so3jax._quadrotor import DIFFTUNE_INERTIA, DIFFTUNE_MASS, PAPER_GAINS
from so3jax._sweep import RUN_FIELDS

SEED = scenes.seed()
PERIOD, DT, N_STEPS = 0.02, 0.02, 150  # a 3 s horizon, one step per hold
SIGMA = {"attitude": 0.05, "rate": 0.1}
K_R, K_OMEGA = [8.81, 20.0], [2.54, 8.0]  # two gain pairs (grid=False)
SCALES = [0.0, 1.0, 4.0]
N_ATT = 3
KEY = 7
KW = dict(
    grid=False, key=KEY, n_attitudes=N_ATT, dt=DT, n_steps=N_STEPS, scalarize=False,
    progress=False,
)  # fmt: skip


def tracking(noise=None, R0=None, Omega0=(0.0, 0.0, 0.0), gains=scenes.SEED_GAINS):
    """The seed's body and reference under 50 Hz sampled control."""
    R0 = SEED.y0.R[0] if R0 is None else R0
    return scenes.tracking(
        SEED.body,
        s.GeometricGains(*gains),
        R0,
        jnp.asarray(Omega0),
        SEED.y0.R[1],
        SEED.reference,
        control_period=PERIOD,
        noise=noise,
    )


def documented_key(key, a):
    """The noise key of the runs from attitude ``a``, by the rule the sweep documents."""
    return jax.random.fold_in(jax.random.fold_in(jax.random.key(key), a), 2**31 - 1)


_simulate = eqx.filter_jit(lambda sc, method, dt, n: s.simulate(sc, method, dt, n, scalarize=False))


@pytest.fixture(scope="module")
def noisy():
    return tracking(s.SensorNoise(**SIGMA, key=0))


@pytest.fixture(scope="module")
def base(noisy):
    """2 gain pairs x (3 noise scales x 3 attitudes) runs, in one chunk."""
    return s.sweep(noisy, K_R, K_OMEGA, params={"noise_scale": SCALES}, **KW)


def test_runs_equal_simulate_with_the_documented_key(base):
    assert base.params["noise_scale"].shape == (len(SCALES) * N_ATT,)
    # Both gain pairs, and the noise scales 1 and 4, from attitude a = 1: the same key
    # for all four runs (common random numbers), the noise scaled by c.
    for g in (0, 1):
        for p in (1, 2):
            a = 1
            i = p * N_ATT + a
            c = base.params["noise_scale"][i]
            noise = s.SensorNoise(
                **{k: c * v for k, v in SIGMA.items()}, key=documented_key(KEY, a)
            )
            sc = tracking(noise, base.R0[i], base.Omega0[i], (K_R[g], K_OMEGA[g]))
            tr = _simulate(sc, s.RKMK4(), DT, N_STEPS)
            psi = np.asarray(s.attitude_error_function(tr.R, tr.Rd))
            assert base.final_psi[g, i] == pytest.approx(psi[-1], rel=1e-10, abs=1e-14)
            assert base.cost[g, i] == pytest.approx(float(s.tracking_cost(tr, sc)), rel=1e-10)
            peak = np.linalg.norm(np.asarray(tr.M), axis=-1).max()
            assert base.peak_torque[g, i] == pytest.approx(peak, rel=1e-10)


def test_different_starts_read_different_noise(base):
    k0, k1 = (jax.random.key_data(documented_key(KEY, a)) for a in (0, 1))
    assert not np.array_equal(np.asarray(k0), np.asarray(k1))
    # The run from attitude 1 at noise scale 4, with the key of attitude 2 instead: another
    # run (the key matters, and it is the attitude's own).
    i = 2 * N_ATT + 1
    sigma = {k: 4.0 * v for k, v in SIGMA.items()}
    R0, W0 = base.R0[i], base.Omega0[i]
    own = tracking(s.SensorNoise(**sigma, key=documented_key(KEY, 1)), R0, W0, (K_R[0], K_OMEGA[0]))
    other = eqx.tree_at(lambda z: z.noise.key, own, documented_key(KEY, 2))
    psi = [
        float(s.attitude_error_function(t.R, t.Rd)[-1])
        for t in (_simulate(own, s.RKMK4(), DT, N_STEPS), _simulate(other, s.RKMK4(), DT, N_STEPS))
    ]
    assert psi[0] == pytest.approx(base.final_psi[0, i], rel=1e-10)
    assert abs(psi[1] / psi[0] - 1) > 1e-3


def test_chunked_equals_unchunked_and_resumes(noisy, base, tmp_path):
    done = []
    kw = dict(KW, params={"noise_scale": SCALES}, chunk_size=4, results_dir=tmp_path)
    chunked = s.sweep(noisy, K_R, K_OMEGA, on_chunk=lambda c, n: done.append(c), **kw)
    assert done == [0, 1, 2, 3, 4]  # 18 runs in chunks of 4
    for f in RUN_FIELDS:  # another batch size: another program, the same runs to round-off
        np.testing.assert_allclose(getattr(chunked, f), getattr(base, f), rtol=1e-12, atol=1e-15)
    # The chunk files of a noisy scene load back, whatever the scene's own noise key (the
    # runs do not read it).
    other = eqx.tree_at(lambda z: z.noise.key, noisy, jax.random.key(99))
    again = s.sweep(other, K_R, K_OMEGA, on_chunk=lambda c, n: done.append(c), **kw)
    assert done == [0, 1, 2, 3, 4]
    for f in RUN_FIELDS:
        np.testing.assert_array_equal(getattr(again, f), getattr(chunked, f))


def test_zero_scale_is_the_noise_free_sweep(base, monkeypatch):
    calls, run_chunk = [], _sweep._run_chunk

    def recorded(*args):
        calls.append(len(args))
        return run_chunk(*args)

    monkeypatch.setattr(_sweep, "_run_chunk", recorded)
    clean = s.sweep(tracking(), K_R, K_OMEGA, **KW)
    # A scene without noise is called as before noise existed: no noise argument.
    assert set(calls) == {13}
    for f in RUN_FIELDS:  # noise scale 0 is the first N_ATT columns
        np.testing.assert_allclose(
            getattr(base, f)[:, :N_ATT], getattr(clean, f), rtol=1e-12, atol=1e-14, err_msg=f
        )
    assert np.all(clean.final_psi < 1e-3)  # both gain pairs settle from every start


def test_more_noise_raises_the_final_attitude_error(base):
    psi = base.final_psi.reshape(2, len(SCALES), N_ATT)
    mean = psi.mean(axis=(0, 2))
    assert mean[0] < mean[1] < mean[2]
    assert mean[2] > 3 * mean[1]
    assert base.outcome_counts()["diverged"] == 0


def test_heatmap_axis_is_labelled_with_its_unit(base):
    fig = plot.sweep_heatmaps(base, x="noise_scale", y="k_R")
    assert fig.axes[0].get_xlabel() == "sensor noise scale (x the scene's SensorNoise std)"
    matplotlib.pyplot.close("all")


def test_bad_noise_scale_is_named(noisy):
    quad = scenes.quadrotor(
        DIFFTUNE_MASS,
        DIFFTUNE_INERTIA,
        s.QuadrotorGains(*PAPER_GAINS),
        s.HoverReference(),
        control_period=0.01,
    )
    zero = tracking(s.SensorNoise(attitude=0.0, key=0))  # no noise: the noise-free scene
    for scene in (tracking(), quad, zero):
        with pytest.raises(ValueError, match=r"params\['noise_scale'\].*has none"):
            s.sweep(scene, [1.0], [1.0], params={"noise_scale": [1.0]}, progress=False)
    with pytest.raises(ValueError, match=r"params\['noise_scale'\] must be >= 0"):
        s.sweep(noisy, [1.0], [1.0], params={"noise_scale": [1.0, -0.5]}, progress=False)
    with pytest.raises(ValueError, match=r"params\['noise_scale'\] must have shape \('P',\)"):
        s.sweep(noisy, [1.0], [1.0], params={"noise_scale": [[1.0, 2.0, 3.0]]}, progress=False)


def test_quadrotor_runs_equal_simulate_with_the_documented_key():
    sigma = dict(attitude=0.02, rate=0.05, position=0.02, velocity=0.05)

    def quad(noise, R0=None, Omega0=(0.0, 0.0, 0.0)):
        return scenes.quadrotor(
            DIFFTUNE_MASS,
            DIFFTUNE_INERTIA,
            s.QuadrotorGains(*PAPER_GAINS),
            s.HoverReference(),
            R0=R0,
            Omega0=Omega0,
            control_period=0.01,
            noise=noise,
        )

    kw = dict(dt=0.01, n_steps=60, save_every=10, scalarize=False, progress=False)
    k_R, k_O = PAPER_GAINS[2], PAPER_GAINS[3]
    r = s.sweep(
        quad(s.SensorNoise(**sigma, key=0)), [k_R], [k_O], key=3, n_attitudes=2,
        params={"noise_scale": [2.0]}, **kw,
    )  # fmt: skip
    a = i = 1
    noise = s.SensorNoise(**{k: 2.0 * v for k, v in sigma.items()}, key=documented_key(3, a))
    tr = s.simulate(quad(noise, r.R0[i], r.Omega0[i]), s.RKMK4(), 0.01, 60, 10, scalarize=False)
    assert r.final_psi[0, i] == pytest.approx(float(tr.extras["Psi"][-1]), rel=1e-10)
    e = float(np.linalg.norm(np.asarray(tr.extras["e_x"][-1])))
    assert r.metrics["final_position_error"][0, i] == pytest.approx(e, rel=1e-10)


def test_default_layout_falls_back_silently():
    """A step the scalarizer does not take (a wind interpolated by ``jnp.interp``, whose
    search is a loop) runs as the array program: silently in the sweep's default layout,
    nobody asked for the scalarized one; said where it was asked for. (Different
    horizons: each call traces its own program.)"""
    import warnings

    times, speeds = jnp.linspace(0.0, 0.2, 9), jnp.linspace(1.0, 2.0, 9) ** 2

    def gust(t):
        return jnp.stack([jnp.interp(t, times, speeds), 0.0 * t, 0.0 * t])

    quad = scenes.quadrotor_recovery(control_period=0.01)
    quad = scenes.quadrotor(
        quad.vehicle.mass, quad.vehicle.body, quad.gains, quad.reference, R0=quad.y0.R[0],
        control_period=0.01, drag=0.1, wind=gust,
    )  # fmt: skip
    kw = dict(n_attitudes=2, dt=0.01, key=0, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        quiet = s.sweep(quad, [8.81], [2.54], n_steps=4, **kw)
    with pytest.warns(UserWarning, match="running the array program"):
        said = s.sweep(quad, [8.81], [2.54], n_steps=5, scalarize=True, **kw)
    assert np.all(np.isfinite(quiet.cost)) and np.all(np.isfinite(said.cost))
