"""Sweeps over scene parameters: inertia per axis, disturbance, initial rates, reference."""

import dataclasses

import numpy as np
import pytest

import so3jax as s
from so3jax._sweep_params import Disturbed

SEED = s.scenes.seed()
PARAMS = {
    # Per-axis scales that keep the seed's moments a physical body (triangle inequality).
    "inertia_scale": [[0.9, 1.0, 1.1], [1.1, 1.0, 0.9]],
    "disturbance": [[0.0, 0.0, 0.0], [0.05, -0.02, 0.01]],
    "Omega0": [[0.1, 0.0, -0.2]],
    "reference_amplitude": [0.5, 2.0],
}
KW = dict(key=3, n_attitudes=2, dt=1e-2, n_steps=200, progress=False, scalarize=False)


def direct(i, r):
    """Run ``i`` of a one-gain-pair sweep, built by hand from the public scene constructors."""
    scale = np.sqrt(r.params["inertia_scale"][i])
    J = scale[:, None] * np.asarray(SEED.body.inertia) * scale[None, :]
    ref = s.SinusoidalRate(amplitude=0.5 * r.params["reference_amplitude"][i])
    gains = s.GeometricGains(float(r.k_R[0]), float(r.k_Omega[0]))
    base = s.scenes.tracking(J, gains, r.R0[i], r.params["Omega0"][i], np.eye(3), ref)
    return Disturbed(
        body=base.body,
        controller=base.controller,
        reference=base.reference,
        y0=base.y0,
        disturbance=np.asarray(r.params["disturbance"][i]),
    )


def test_parameter_sweep_equals_a_loop_of_simulate():
    r = s.sweep(SEED, [8.81], [2.54], params=PARAMS, chunk_size=16, **KW)
    assert r.cost.shape == (1, 2 * 2 * 1 * 2 * 2)  # combinations x attitudes
    assert set(r.params) == set(PARAMS)
    # Column i = p * n_attitudes + a: each combination sees the same two attitudes.
    np.testing.assert_array_equal(r.R0[0::2], np.broadcast_to(r.R0[0], r.R0[0::2].shape))
    combos = {tuple(np.concatenate([np.ravel(r.params[k][i]) for k in PARAMS])) for i in range(16)}
    assert len(combos) == 8
    for i in range(r.cost.shape[1]):
        sc = direct(i, r)
        traj = s.simulate(sc, s.RKMK4(), 1e-2, 200)
        psi = np.asarray(s.attitude_error_function(traj.R, traj.Rd))
        assert r.final_psi[0, i] == pytest.approx(psi[-1], rel=1e-10, abs=1e-14)
        assert r.cost[0, i] == pytest.approx(float(s.tracking_cost(traj, sc)), rel=1e-10)
        peak = np.linalg.norm(np.asarray(traj.M), axis=-1).max()
        assert r.peak_torque[0, i] == pytest.approx(peak, rel=1e-10)
    # The parameters matter: the disturbance and the amplitude change the cost.
    assert np.unique(np.round(r.cost, 8)).size > 4
    # Zipped (sampled) parameters: the same length, one column block per sample.
    z = s.sweep(
        SEED,
        [8.81],
        [2.54],
        params={"inertia_scale": [1.0, 1.1], "reference_amplitude": [1.0, 0.5]},
        param_grid=False,
        chunk_size=16,
        **KW,
    )
    assert z.cost.shape == (1, 4)
    np.testing.assert_array_equal(z.params["inertia_scale"][2], [1.1, 1.1, 1.1])
    sc = direct(3, _with_defaults(z))
    traj = s.simulate(sc, s.RKMK4(), 1e-2, 200)
    assert z.cost[0, 3] == pytest.approx(float(s.tracking_cost(traj, sc)), rel=1e-10)


def test_parameter_sweep_saves_and_resumes(tmp_path):
    params = {"reference_amplitude": [1.0, 0.5]}
    kw = dict(params=params, chunk_size=16, results_dir=tmp_path / "runs", **KW)
    r = s.sweep(SEED, [8.81], [2.54], **kw)
    again = s.sweep(SEED, [8.81], [2.54], **kw)  # loaded from the chunk files
    np.testing.assert_array_equal(again.cost, r.cost)
    with pytest.raises(ValueError, match="different sweep"):
        s.sweep(SEED, [8.81], [2.54], **{**kw, "params": {"reference_amplitude": [1.0, 0.4]}})
    r.save(tmp_path / "r.npz")
    loaded = s.SweepResult.load(tmp_path / "r.npz")
    np.testing.assert_array_equal(loaded.params["reference_amplitude"], [1.0, 1.0, 0.5, 0.5])


def test_bad_parameters_are_named():
    def bad(params, match, **kw):
        with pytest.raises(ValueError, match=match):
            s.sweep(SEED, [1.0], [1.0], params=params, progress=False, **kw)

    bad({"mass": [1.0]}, "unknown parameter 'mass'.*inertia_scale")
    bad({"inertia_scale": [[1.0, 1.0]]}, r"params\['inertia_scale'\] must have shape")
    bad({"disturbance": [0.1, 0.2]}, r"params\['disturbance'\] must have shape \('P', 3\)")
    bad({"inertia_scale": [1.0, -0.2]}, r"inertia_scale'\] must be > 0")
    bad({"reference_amplitude": [np.nan]}, "must be finite")
    bad(
        {"inertia_scale": [1.0, 1.1], "reference_amplitude": [1.0]},
        "same length.*inertia_scale: 2, reference_amplitude: 1",
        param_grid=False,
    )


def test_command_line_parameter_options(capsys):
    from so3jax._cli_sweep import sweep_main, sweep_parser

    args = sweep_parser().parse_args(
        [
            "--inertia-scale",
            "0.8",
            "1.2",
            "--disturbance",
            "0",
            "0",
            "0.1",
            "--omega0",
            "1",
            "0",
            "0",
        ]
    )
    assert args.inertia_scale == [0.8, 1.2] and args.disturbance == [[0.0, 0.0, 0.1]]
    assert args.omega0 == [[1.0, 0.0, 0.0]]
    for argv, match in (
        (["--inertia-scale", "-1"], "--inertia-scale"),
        (["--inertia-scale", "1", "--inertia-scale-axes", "1", "1", "1"], "not both"),
    ):
        with pytest.raises(SystemExit) as e:
            sweep_main(argv)
        assert e.value.code == 2 and match in capsys.readouterr().err
    with pytest.warns(UserWarning, match="triangle inequality"):
        s.sweep(SEED, [1.0], [1.0], params={"inertia_scale": [[0.5, 0.5, 2.0]]}, **KW)


def test_distributions_are_sampled_per_attitude():
    """A parameter given as a function ``key -> value`` is drawn once per initial attitude
    (sample ``a`` independent of the number of attitudes, the same for every gain pair)."""
    import jax

    from so3jax._sweep_params import draw

    dist = {"disturbance": lambda k: 0.05 * jax.random.normal(k, (3,))}
    r = s.sweep(SEED, [8.81, 20.0], [2.54], params=dist, chunk_size=4, **KW)
    d = r.params["disturbance"]
    assert d.shape == (2, 3) and not np.allclose(d[0], d[1])
    key = jax.random.key(3)
    np.testing.assert_array_equal(draw(dist, key, 4)["disturbance"][:2], d)
    for i in range(2):
        sc = direct(i, _with_defaults(r))
        traj = s.simulate(sc, s.RKMK4(), 1e-2, 200)
        assert r.cost[0, i] == pytest.approx(float(s.tracking_cost(traj, sc)), rel=1e-10)
    with pytest.raises(ValueError, match=r"params\['Omega0'\]: a distribution must return"):
        s.sweep(SEED, [1.0], [1.0], params={"Omega0": lambda k: jax.random.normal(k, (2,))}, **KW)


def _with_defaults(r):
    """``r`` with the parameters it did not sweep at their neutral values (for `direct`)."""
    n = r.cost.shape[1]
    defaults = {
        "inertia_scale": np.ones((n, 3)),
        "disturbance": np.zeros((n, 3)),
        "Omega0": np.zeros((n, 3)),
        "reference_amplitude": np.ones(n),
    }
    return dataclasses.replace(r, params={**defaults, **r.params})
