"""One rule for bad values: a `ValueError` naming the argument when eager; under `jit` /
`vmap`, a run whose `Status` names the cause, NaN from its start, the rest of the batch
untouched (docs/conventions.md, "Bad input")."""

from __future__ import annotations

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import so3jax
from so3jax import scenes
from so3jax._trajectory import (
    BAD_DT,
    BAD_R0,
    BAD_RD0,
    COMMAND_UNDEFINED,
    NONFINITE,
    NONFINITE_PARAMETER,
    NONFINITE_START,
    OK,
)
from so3jax._tune import with_gains

N, EVERY, DT = 20, 5, 1e-2
METHOD = so3jax.RKMK4()
# Lee, Leok & McClamroch (CDC 2010), the recovery's start as printed: ||R^T R - I|| = 1.95e-5.
PAPER_R0 = np.array([[1.0, 0.0, 0.0], [0.0, -0.9995, -0.0314], [0.0, 0.0314, -0.9995]])


def _seed_parts():
    sc = scenes.seed()
    return sc.body.inertia, sc.controller.gains, sc.y0.x[:3], sc.y0.R[1], sc.reference


def _good_R():
    return so3jax.from_euler_zyx(0.3, -0.2, 0.1)


def _assert_failed_from_start(traj, i, code):
    """Run ``i`` of a batch: status ``code`` before the first step, every point NaN."""
    assert int(traj.status.code[i]) == code
    assert int(traj.status.step[i]) == -1
    assert np.all(np.isnan(np.asarray(traj.R[i])))
    assert np.all(np.isnan(np.asarray(traj.Omega[i])))
    assert so3jax.Status.codes[code] in traj.status.message()


def _assert_equal_unbatched(batched, i, single):
    """Run ``i`` of a batch equals its own run (to round-off: a batch is another program)."""
    assert int(batched.status.code[i]) == int(single.status.code) == OK
    np.testing.assert_allclose(batched.R[i], single.R, rtol=0, atol=1e-13)
    np.testing.assert_allclose(batched.Omega[i], single.Omega, rtol=0, atol=1e-12)


def test_dt_eager_and_under_jit_vmap():
    sc = scenes.seed()
    for bad in (-1e-2, 0.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="dt must be positive and finite"):
            so3jax.simulate(sc, METHOD, dt=bad, n_steps=N)
    run = jax.jit(
        jax.vmap(lambda h: so3jax.simulate(sc, METHOD, dt=h, n_steps=N, save_every=EVERY))
    )
    traj = run(jnp.array([DT, -DT, jnp.nan, 0.0]))
    for i in (1, 2, 3):
        _assert_failed_from_start(traj, i, BAD_DT)
    _assert_equal_unbatched(traj, 0, so3jax.simulate(sc, METHOD, DT, N, save_every=EVERY))
    # A traced dt alone (the case that used to end in an XLA callback error).
    single = jax.jit(lambda h: so3jax.simulate(sc, METHOD, dt=h, n_steps=N))(-DT)
    assert int(single.status.code) == BAD_DT
    assert single.status.message() == "dt is not positive and finite (before the first step)"
    # The cost of such a run is NaN, not a number from a backwards run.
    cost = jax.jit(lambda h: so3jax.rollout_cost(sc, METHOD, h, N))
    assert np.isnan(float(cost(-DT))) and np.isfinite(float(cost(DT)))


def test_R0_not_a_rotation_eager_and_under_jit_vmap():
    sc = scenes.seed()
    with pytest.raises(ValueError, match="R0 is not a rotation"):
        so3jax.simulate(sc, METHOD, DT, N, R0=PAPER_R0)
    J, gains, W0, Rd0, ref = _seed_parts()
    with pytest.raises(ValueError, match="R0 is not a rotation"):
        scenes.tracking(J, gains, PAPER_R0, W0, Rd0, ref)
    Rs = jnp.stack([_good_R(), jnp.asarray(PAPER_R0), -_good_R(), _good_R().at[0, 0].set(jnp.nan)])
    # Through simulate's R0 ...
    run = jax.jit(jax.vmap(lambda R: so3jax.simulate(sc, METHOD, DT, N, EVERY, R0=R)))
    traj = run(Rs)
    _assert_failed_from_start(traj, 1, BAD_R0)
    _assert_failed_from_start(traj, 2, BAD_R0)  # orthogonal, det = -1
    _assert_failed_from_start(traj, 3, NONFINITE_START)
    _assert_equal_unbatched(traj, 0, so3jax.simulate(sc, METHOD, DT, N, EVERY, R0=Rs[0]))
    # ... and through a scene built under the trace.
    build = jax.vmap(
        lambda R: so3jax.simulate(scenes.tracking(J, gains, R, W0, Rd0, ref), METHOD, DT, N, EVERY)
    )
    traj = jax.jit(build)(Rs[:2])
    _assert_failed_from_start(traj, 1, BAD_R0)
    _assert_equal_unbatched(traj, 0, so3jax.simulate(sc, METHOD, DT, N, EVERY, R0=Rs[0]))


def test_Rd0_not_a_rotation_and_nonfinite_rate():
    J, gains, W0, Rd0, ref = _seed_parts()
    R0 = _good_R()
    with pytest.raises(ValueError, match="Rd0 is not a rotation"):
        scenes.tracking(J, gains, R0, W0, PAPER_R0, ref)
    with pytest.raises(ValueError, match="Omega0 contains NaN"):
        scenes.tracking(J, gains, R0, jnp.array([0.0, jnp.nan, 0.0]), Rd0, ref)

    def one(Rd, W):
        return so3jax.simulate(scenes.tracking(J, gains, R0, W, Rd, ref), METHOD, DT, N, EVERY)

    Rds = jnp.stack([jnp.eye(3), jnp.asarray(PAPER_R0), jnp.eye(3)])
    Ws = jnp.stack([W0, W0, W0.at[1].set(jnp.nan)])
    traj = jax.jit(jax.vmap(one))(Rds, Ws)
    _assert_failed_from_start(traj, 1, BAD_RD0)
    _assert_failed_from_start(traj, 2, NONFINITE_START)
    single = so3jax.simulate(
        scenes.tracking(J, gains, R0, W0, jnp.eye(3), ref), METHOD, DT, N, EVERY
    )
    _assert_equal_unbatched(traj, 0, single)


def test_nonfinite_gain_eager_and_under_jit_vmap():
    J, gains, W0, Rd0, ref = _seed_parts()
    R0 = _good_R()
    with pytest.raises(ValueError, match="k_R must be finite"):
        so3jax.GeometricGains(jnp.nan, 2.54)

    def one(k):
        sc = scenes.tracking(J, so3jax.GeometricGains(k, 2.54), R0, W0, Rd0, ref)
        return so3jax.simulate(sc, METHOD, DT, N, EVERY)

    traj = jax.jit(jax.vmap(one))(jnp.array([8.81, jnp.nan, jnp.inf]))
    _assert_failed_from_start(traj, 1, NONFINITE_PARAMETER)
    _assert_failed_from_start(traj, 2, NONFINITE_PARAMETER)
    _assert_equal_unbatched(traj, 0, one(8.81))


class Heading(eqx.Module):
    """Hover at the origin with heading ``b1`` (an array: one compilation for every heading)."""

    b1: jax.Array

    def __call__(self, t):
        return jnp.zeros(3) * t, self.b1 + 0.0 * t


def _quad(b1, control_period):
    base = scenes.quadrotor_circle()
    return scenes.quadrotor(
        base.vehicle.mass,
        base.vehicle.body.inertia,
        base.gains,
        Heading(b1),
        control_period=control_period,
    )


@pytest.mark.parametrize("control_period", [None, 0.005])
def test_quadrotor_heading_parallel_to_thrust(control_period):
    """Hovering, the thrust axis is e3: a heading b1_d = e3 leaves Rc undefined."""
    dt, n = 0.0025, 8

    def run(b1):
        return so3jax.simulate(_quad(b1, control_period), so3jax.LieEuler(), dt, n, 2)

    e1, e3 = jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 0.0, 1.0])
    eager = run(e3)
    assert int(eager.status.code) == COMMAND_UNDEFINED
    assert "b1_d parallel to the thrust axis" in eager.status.message()
    assert np.all(np.isnan(np.asarray(eager.extras["x"][1:])))
    batch = jax.jit(jax.vmap(run))(jnp.stack([e1, e3]))
    assert batch.status.code.tolist() == [OK, COMMAND_UNDEFINED]
    single = run(e1)
    for name in ("x", "v"):
        np.testing.assert_allclose(batch.extras[name][0], single.extras[name], atol=1e-12)
    np.testing.assert_allclose(batch.R[0], single.R, atol=1e-13)


def test_batched_status_message_counts_and_first_failure():
    """A step past the stability limit diverges mid-run: the summary counts and locates it."""
    sc = scenes.seed()
    k_Omega = jnp.array([2.54, 2.54, 2.54, 400.0, 900.0])  # damping past Lie-Euler's limit
    run = jax.jit(
        jax.vmap(
            lambda k: so3jax.simulate(with_gains(sc, 8.81, k), so3jax.LieEuler(), 0.05, 200, 10)
        )
    )
    traj = run(k_Omega)
    code = np.asarray(traj.status.code)
    assert code[:3].tolist() == [OK] * 3 and np.all(code[3:] == NONFINITE)
    msg = traj.status.message()
    assert msg.startswith("3 of 5 runs finite to the end; 2 runs: the state stopped being finite")
    i = 3
    step = int(traj.status.step[i])
    assert step >= 0 and float(traj.status.t[i]) == pytest.approx(step * 0.05)
    assert f"first failure: run {i}, the state stopped being finite at step {step}" in msg
    # The points up to the last good state are finite, the rest NaN.
    good = np.isfinite(np.asarray(traj.Omega[i, :, 0]))
    assert good.tolist() == (np.arange(traj.t.shape[-1]) * 10 <= step).tolist()
    # Every code a run can end with has its documented meaning.
    for c in (
        OK,
        NONFINITE,
        BAD_DT,
        BAD_R0,
        BAD_RD0,
        NONFINITE_START,
        NONFINITE_PARAMETER,
        COMMAND_UNDEFINED,
    ):
        assert c in so3jax.Status.codes


def test_gain_and_start_shapes_at_every_entry_point():
    sc = scenes.seed()
    R0 = so3jax.random_rotation(jax.random.PRNGKey(0), (2,))
    W0 = jnp.zeros((2, 3))
    with pytest.raises(ValueError, match="must be a scalar or a 3-vector") as ref:
        so3jax.GeometricGains(jnp.array([1.0, 2.0]), 3.0)
    expected = re.escape(str(ref.value).split(" got")[0].replace("GeometricGains.", ""))
    with pytest.raises(ValueError, match=expected):
        so3jax.expected_cost(sc, jnp.array([1.0, 2.0]), 3.0, R0, W0, METHOD, DT, N)
    with pytest.raises(ValueError, match="k_Omega must be a scalar or a 3-vector"):
        so3jax.expected_cost(sc, 1.0, jnp.ones((2, 3)), R0, W0, METHOD, DT, N)
    with pytest.raises(ValueError, match="gains0.k_R must be a scalar or a 3-vector"):
        so3jax.tune(sc, (jnp.array([1.0, 2.0]), 3.0), n_iter=0)
    with pytest.raises(ValueError, match=r"R0 must have shape \(B, 3, 3\)"):
        so3jax.expected_cost(sc, 1.0, 1.0, R0[0], W0, METHOD, DT, N)
    with pytest.raises(ValueError, match=r"Omega0 must have shape \(B, 3\)"):
        so3jax.expected_cost(sc, 1.0, 1.0, R0, W0[0], METHOD, DT, N)
    with pytest.raises(ValueError, match="same number of starts"):
        so3jax.expected_cost(sc, 1.0, 1.0, R0, W0[:1], METHOD, DT, N)
    with pytest.raises(ValueError, match=r"k_R must have shape \(G,\) or \(G, 3\)"):
        so3jax.stable_dt(METHOD, sc.body.inertia, jnp.ones((2, 2)), jnp.ones(2))
    with pytest.raises(ValueError, match="same number of gain sets"):
        so3jax.stable_dt(METHOD, sc.body.inertia, jnp.ones(2), jnp.ones(3))
    with pytest.raises(ValueError, match="inertia must be positive definite"):
        so3jax.stable_dt(METHOD, jnp.array([1.0, -1.0, 1.0]), 1.0, 1.0)
    with pytest.raises(ValueError, match="inertia must be a"):
        so3jax.stable_dt(METHOD, jnp.ones(2), 1.0, 1.0)
    with pytest.raises(ValueError, match=r"k_R must have shape \(n,\)"):
        so3jax.sweep(sc, jnp.ones((2, 2)), jnp.ones(2), n_attitudes=2, n_steps=N)
    with pytest.raises(ValueError, match=r"R0\[1\] is not a rotation"):
        so3jax.tune(sc, cost=lambda tr: 0.0, starts=jnp.stack([R0[0], jnp.asarray(PAPER_R0)]))


def test_tune_over_starts_is_the_mean_of_single_start_gradients():
    """One SGD step of unit rate moves the gains by minus the mean of the single-start
    gradients, each taken by plain `jax.grad` of the same cost on `simulate`."""
    sc = scenes.seed()
    R0 = so3jax.random_rotation(jax.random.PRNGKey(1), (3,))
    W0 = 0.1 * jax.random.normal(jax.random.PRNGKey(2), (3, 3))
    n = 12

    def cost(tr):
        psi = so3jax.attitude_error_function(tr.R, tr.Rd)
        return jnp.mean(psi) + 1e-3 * jnp.mean(tr.M**2)

    result = so3jax.tune(
        sc,
        cost=cost,
        starts=(R0, W0),
        dt=DT,
        n_steps=n,
        n_iter=1,
        method=so3jax.LieEuler(),
        optimizer=optax.sgd(1.0),
    )
    g0 = sc.controller.gains
    step = jax.tree.map(lambda a: a[1] - a[0], result.gains_history)

    @jax.jit
    def single(R, W):
        def loss(g):
            s = eqx.tree_at(lambda s: s.controller.gains, sc, g)
            return cost(so3jax.simulate(s, so3jax.LieEuler(), DT, n, R0=R, Omega0=W))

        return jax.grad(loss)(g0)

    grads = [single(R0[b], W0[b]) for b in range(3)]
    mean = jax.tree.map(lambda *g: sum(g) / 3, *grads)
    np.testing.assert_allclose(step.k_R, -mean.k_R, rtol=1e-9)
    np.testing.assert_allclose(step.k_Omega, -mean.k_Omega, rtol=1e-9)
    # The costs averaged are those of the starts, not of the scene's own start.
    costs = [
        cost(so3jax.simulate(sc, so3jax.LieEuler(), DT, n, R0=R0[b], Omega0=W0[b]))
        for b in range(3)
    ]
    assert result.cost_history[0] == pytest.approx(np.mean(costs), rel=1e-12)


def test_adaptive_runs_follow_the_same_rule():
    """Adaptive steps (diffrax's controller): a traced non-rotation start is a status too."""
    sc = scenes.free_body(jnp.array([1.0, 2.0, 3.0]), jnp.eye(3), jnp.array([0.1, 1.0, 0.1]))

    def run(R):
        return so3jax.simulate(sc, so3jax.RKMK45(), t1=0.2, rtol=1e-8, atol=1e-8, saveat=3, R0=R)

    with pytest.raises(ValueError, match="R0 is not a rotation"):
        run(PAPER_R0)
    Rs = jnp.stack([_good_R(), jnp.asarray(PAPER_R0)])
    traj = jax.jit(jax.vmap(run))(Rs)
    _assert_failed_from_start(traj, 1, BAD_R0)
    _assert_equal_unbatched(traj, 0, run(Rs[0]))
