"""Sweeps of robustness: torque limits, rotor limits and lag, and wind, as `sweep` params.

Each swept value is checked against a scene built with that value by the public
constructors (`scenes.tracking(..., max_torque=...)`, `scenes.quadrotor(..., rotors=
Rotors(thrust_max=..., time_constant=...), drag=..., wind=...)`) and run by `simulate`;
the physics sets the direction of the effects (a clipped torque bounds the peak, wind
pushes the vehicle off its hover point, a slower rotor recovers worse).
"""

import matplotlib

matplotlib.use("Agg")

import jax.numpy as jnp
import numpy as np
import pytest

import so3jax as s
from so3jax import plot
from so3jax._quadrotor import DIFFTUNE_INERTIA, DIFFTUNE_MASS, PAPER_GAINS
from so3jax._sweep_params import apply_params, check_params, prepare_scene

SEED = s.scenes.seed()
G = 9.81
ARM, TORQUE_COEFFICIENT, DRAG = 0.315, 0.02, 2.0
QKW = dict(dt=0.01, n_steps=300, save_every=10, scalarize=False, progress=False)
QPARAMS = {
    "thrust_to_weight": [1.5, 3.0],
    "time_constant": [0.02, 0.08],
    "wind_speed": [[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]],
}


def rotor_scene(thrust_max=30.0, time_constant=0.05, R0=None, wind=None, k=PAPER_GAINS):
    """Hover at the origin under the paper's gains, 100 Hz control, lagged rotors, drag."""
    return s.scenes.quadrotor(
        DIFFTUNE_MASS,
        DIFFTUNE_INERTIA,
        s.QuadrotorGains(*k),
        s.HoverReference(),
        R0=R0,
        control_period=0.01,
        rotors=s.Rotors(
            ARM, TORQUE_COEFFICIENT, thrust_max=thrust_max, time_constant=time_constant
        ),
        drag=DRAG,
        wind=wind,
    )


@pytest.fixture(scope="module")
def quad():
    """2 x 2 x 2 combinations x 2 attitudes (the second, 37 degrees off level, recovers)."""
    return s.sweep(
        rotor_scene(), [8.81], [2.54], key=1, n_attitudes=2, params=QPARAMS,
        position_threshold=0.2, **QKW,
    )  # fmt: skip


def test_max_torque_sweep_equals_limited_tracking_scenes():
    limits = [[0.2, 0.2, 0.2], [0.1, 0.4, 1.0], [50.0, 50.0, 50.0]]
    kw = dict(key=4, n_attitudes=2, dt=1e-2, n_steps=150, scalarize=False, progress=False)
    r = s.sweep(SEED, [8.81], [2.54], params={"max_torque": limits}, **kw)
    assert r.params["max_torque"].shape == (6, 3)
    gains = s.GeometricGains(8.81, 2.54)
    for i in range(6):
        lim = r.params["max_torque"][i]
        sc = s.scenes.tracking(
            SEED.body, gains, r.R0[i], SEED.y0.x[:3], SEED.y0.R[1], SEED.reference, max_torque=lim
        )
        tr = s.simulate(sc, s.RKMK4(), 1e-2, 150)
        M = np.asarray(tr.M)
        assert np.all(np.abs(M) <= lim * (1 + 1e-12))  # the applied torque is clipped
        psi = np.asarray(s.attitude_error_function(tr.R, tr.Rd))
        assert r.final_psi[0, i] == pytest.approx(psi[-1], rel=1e-10, abs=1e-14)
        assert r.cost[0, i] == pytest.approx(float(s.tracking_cost(tr, sc)), rel=1e-10)
        assert r.peak_torque[0, i] == pytest.approx(np.linalg.norm(M, axis=-1).max(), rel=1e-10)
    # A limit bounds the peak torque; a loose one leaves the controller's torque alone.
    tight, loose = r.peak_torque[0, :2], r.peak_torque[0, 4:]
    assert np.all(tight <= 0.2 * np.sqrt(3) * (1 + 1e-12)) and np.all(loose > 0.5)
    # A scalar per run stands for all three axes; a scene with a limit has it replaced.
    np.testing.assert_array_equal(
        check_params({"max_torque": [0.5]}, True)["max_torque"], [[0.5] * 3]
    )
    limited = s.scenes.tracking(SEED.body, gains, np.eye(3), np.zeros(3), np.eye(3), max_torque=0.1)
    assert prepare_scene(SEED, {"max_torque": 1}).max_torque.shape == (3,)  # the slot
    assert prepare_scene(limited, {"max_torque": 1}) is limited
    out = apply_params(limited, {"max_torque": np.array([1.0, 2.0, 3.0])})
    np.testing.assert_array_equal(out.max_torque, [1.0, 2.0, 3.0])


def test_rotor_and_wind_sweep_equals_scenes_built_with_those_values(quad):
    r = quad
    assert r.cost.shape == (1, 16) and np.all(r.outcome == 0)
    m, w = DIFFTUNE_MASS, s.CostWeights()
    k = (PAPER_GAINS[0], PAPER_GAINS[1], 8.81, 2.54)
    for i in range(16):
        ratio, tau = r.params["thrust_to_weight"][i], r.params["time_constant"][i]
        sc = rotor_scene(ratio * (m * G / 4.0), tau, r.R0[i], r.params["wind_speed"][i], k)
        tr = s.simulate(sc, s.RKMK4(), 0.01, 300, save_every=10)
        assert bool(tr.status.ok)
        thrust = np.asarray(tr.extras["rotor_thrust"])
        assert thrust.max() <= ratio * m * G / 4 * (1 + 1e-12)
        e = np.linalg.norm(np.asarray(tr.extras["e_x"]), axis=-1)
        psi = np.asarray(tr.extras["Psi"])
        for name, want in (
            ("final_position_error", e[-1]),
            ("max_position_error", e.max()),
            ("min_thrust_axis_up", np.asarray(tr.R)[:, 2, 2].min()),
        ):
            assert r.metrics[name][0, i] == pytest.approx(want, rel=1e-9, abs=1e-12), name
        assert r.final_psi[0, i] == pytest.approx(psi[-1], rel=1e-9, abs=1e-13)
        assert r.peak_torque[0, i] == pytest.approx(np.linalg.norm(tr.M, axis=-1).max(), rel=1e-9)
        f = (e**2 + float(w.psi) * psi
             + float(w.omega) * np.sum(np.asarray(tr.extras["e_Omega"]) ** 2, -1)
             + float(w.effort) * np.sum(np.asarray(tr.M) ** 2, -1))  # fmt: skip
        assert r.cost[0, i] == pytest.approx(np.trapezoid(f, np.asarray(tr.t)), rel=1e-9)


def test_rotor_and_wind_sweep_directions(quad):
    """Column ``((a * 2 + b) * 2 + c) * 2 + i``: thrust-to-weight ``a``, time constant
    ``b``, wind ``c``, attitude ``i``."""
    r = quad

    def metric(name):
        return r.metrics[name].reshape(2, 2, 2, 2)

    final, peak = metric("final_position_error"), metric("max_position_error")
    # From the attitude that recovers, a steady wind leaves a position error that still
    # air does not (drag balanced only by a tilt the position loop pays for in e_x).
    assert np.all(final[:, :, 1, 1] > final[:, :, 0, 1] + 0.1)
    # Slower rotors recover worse: the vehicle strays further.
    assert np.all(peak[:, 1, 0, 1] > peak[:, 0, 0, 1])
    # A lag tau has the mode -1/tau: RKMK4's real interval (2.785) sets the step limit of
    # the held-feedback loop, for the fastest rotors swept.
    assert r.stable_dt[0] == pytest.approx(0.9 * 2.7853 * 0.02, rel=1e-3)
    # The thrust limit matters: the two ratios give other runs.
    assert not np.allclose(r.cost.reshape(2, 8)[0], r.cost.reshape(2, 8)[1])


def test_heatmaps_label_parameter_axes_with_units(quad):
    r = quad
    fig = plot.sweep_heatmaps(r, x="thrust_to_weight", y="time_constant")
    ax = fig.axes[1]
    assert ax.get_xlabel().startswith("thrust-to-weight ratio")
    assert ax.get_ylabel() == "rotor time constant (s)"
    assert "pooled over mean wind (m/s): 2 values" in fig._suptitle.get_text()
    # Each cell pools the runs with its two values.
    shown = np.asarray(ax.collections[0].get_array()).reshape(2, 2)
    p = r.params
    for a, tau in enumerate((0.02, 0.08)):
        for b, ratio in enumerate((1.5, 3.0)):
            cols = (p["time_constant"] == tau) & (p["thrust_to_weight"] == ratio)
            assert shown[a, b] == pytest.approx(1.0 - r.settled[:, cols].mean())
    assert fig.axes[2].get_title() == "median final |e_x| (m)"
    fig = plot.sweep_heatmaps(r, x="wind_speed")  # a 3-vector by its norm; y: k_R
    assert fig.axes[0].get_xlabel() == "|mean wind| (m/s)" and fig.axes[0].get_ylabel() == "k_R"
    fig = plot.sweep_heatmaps(r)  # over the gains: the parameters are pooled
    text = fig._suptitle.get_text()
    assert "pooled over thrust-to-weight ratio" in text and "rotor time constant (s)" in text
    with pytest.raises(ValueError, match="parameter the sweep varied.*got 'max_torque'"):
        plot.sweep_heatmaps(r, x="max_torque")
    matplotlib.pyplot.close("all")


def test_bad_robustness_parameters_are_named():
    def bad(scene, params, match):
        with pytest.raises(ValueError, match=match):
            s.sweep(scene, [1.0], [1.0], params=params, progress=False)

    bad(SEED, {"max_torque": [0.5, -1.0]}, r"params\['max_torque'\] must be > 0")
    bad(SEED, {"max_torque": [[1.0, 2.0]]}, r"params\['max_torque'\] must have shape \(P,\)")
    bad(SEED, {"max_torque": [np.inf]}, r"params\['max_torque'\] must be finite")
    bad(SEED, {"thrust_max": [10.0]}, r"\['thrust_max'\] cannot vary an attitude tracking scene")
    bad(SEED, {"wind_speed": [[1.0, 0, 0]]}, "wind_speed.*vary a quadrotor")
    plain = s.scenes.quadrotor_recovery()
    bad(plain, {"max_torque": [1.0]}, r"\['max_torque'\] cannot vary a quadrotor scene")
    bad(plain, {"thrust_max": [30.0]}, r"params\['thrust_max'\] varies the rotors.*rotors=")
    bad(plain, {"time_constant": [0.02]}, r"params\['time_constant'\] varies the rotors")
    bad(plain, {"wind_speed": [[1.0, 0, 0]]}, r"params\['wind_speed'\] acts through the drag")
    no_lag = s.scenes.quadrotor(
        DIFFTUNE_MASS, DIFFTUNE_INERTIA, s.QuadrotorGains(*PAPER_GAINS), s.HoverReference(),
        rotors=s.Rotors(ARM, TORQUE_COEFFICIENT, thrust_min=12.0, thrust_max=30.0),
    )  # fmt: skip
    bad(no_lag, {"time_constant": [0.02]}, "the scene has none: it must be built with one")
    bad(no_lag, {"thrust_to_weight": [1.1]}, r"thrust_max above the rotors' thrust_min \(12 N\)")
    sc = rotor_scene()
    bad(sc, {"thrust_to_weight": [0.9, 2.0]}, r"\['thrust_to_weight'\] must let the rotors hover")
    bad(sc, {"thrust_max": [5.0]}, r"params\['thrust_max'\] must let the rotors hover")
    bad(sc, {"thrust_max": [0.0]}, r"params\['thrust_max'\] must be > 0")
    bad(sc, {"thrust_max": [30.0], "thrust_to_weight": [2.0]}, "not both")
    bad(sc, {"time_constant": [0.0]}, r"params\['time_constant'\] must be > 0")
    bad(sc, {"wind_speed": [1.0, 2.0]}, r"params\['wind_speed'\] must have shape \('P', 3\)")
    bad(sc, {"thrust_to_weight": lambda k: 0.5}, "must let the rotors hover")
    gusty = rotor_scene(wind=lambda t: jnp.zeros(3) * t)
    bad(gusty, {"wind_speed": [[1.0, 0, 0]]}, "function t -> w\\(t\\) without a `mean`")
