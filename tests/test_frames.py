"""Attitude tangents as three numbers (`so3jax._engine.passes.frames`): the same derivatives as JAX.

Every check compares with JAX's own ``jvp`` of the same function given the dense tangent
``R hat(xi)``, or with JAX's autodiff of the plain array program.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import so3jax as s
from so3jax import _control, _engine, _state, _tune, _updates
from so3jax._engine.passes import frames as F
from so3jax._simulate import _simulate, engine_step, guarded_step, split_groups
from so3jax._tune import with_gains, with_start


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


def _rot(key, shape=()):
    return s.random_rotation(jax.random.PRNGKey(key), shape)


def _vec(key, shape, dtype=jnp.float64):
    return jax.random.normal(jax.random.PRNGKey(key), shape, dtype)


def _dense_in(x, t):
    return F.dense(x, t) if isinstance(t, F.Frame) else t


def _check(fn, xs, ts, tol, frames_out=None):
    """``frame_jvp(fn)`` against ``jax.jvp`` with dense tangents (zeros for ``None``)."""
    real = [jnp.issubdtype(jnp.result_type(x), jnp.inexact) for x in xs]
    dense = [
        jnp.zeros_like(x) if t is None else _dense_in(x, t)
        for x, t, r in zip(xs, ts, real, strict=True)
        if r
    ]

    def fn_real(*a):  # the flags closed over: JAX's jvp takes float0 tangents for them
        it = iter(a)
        return fn(*[next(it) if r else x for x, r in zip(xs, real, strict=True)])

    ref, ref_t = jax.jvp(
        fn_real, tuple(x for x, r in zip(xs, real, strict=True) if r), tuple(dense)
    )
    outs, touts = F.frame_jvp(fn, list(xs), list(ts))
    for o, t, r, rt in zip(outs, touts, ref, ref_t, strict=True):
        np.testing.assert_allclose(o, r, rtol=0, atol=tol)
        got = jnp.zeros_like(o) if t is None else F.dense(o, t)
        assert _rel(got, rt) < tol, (_rel(got, rt), t)
    if frames_out is not None:
        assert [isinstance(t, F.Frame) for t in touts] == frames_out, touts
    return touts


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("update", ["exp", "cayley"])
def test_update_rules_equal_jvp(update, dtype):
    """``R exp(w)`` and ``R cay(u)`` (stacked rotations too), with the rotation's tangent
    a frame or zero and the increment's dense or zero, and the end of a step
    (`_state._advance`), at small and large angles."""
    tol = 1e-13 if dtype == jnp.float64 else 2e-5
    move = _updates._exp_update if update == "exp" else _updates._cay_update
    R = _rot(0, (2,)).astype(dtype)
    for scale in (1e-6, 0.3, 3.0):
        w = (scale * _vec(1, (2, 3))).astype(dtype)
        xi, dw = _vec(2, (2, 3), dtype), _vec(3, (2, 3), dtype)
        for tR, tw in ((F.Frame(xi), dw), (F.Frame(xi), None), (None, dw)):
            if tR is None:  # a zero frame: the rule still gives a frame
                tR = F.Frame(jnp.zeros_like(xi))
            _check(lambda R, w: [move(R, w)], [R, w], [tR, tw], tol, [True])
        x, dx = _vec(4, (4,), dtype), _vec(5, (4,), dtype)
        _check(
            lambda R, w, x, dx: list(_state._advance(R, w, x, dx, update)),
            [R, w, x, dx],
            [F.Frame(xi), dw, None, _vec(6, (4,), dtype)],
            tol,
            [True, False],
        )


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_tracking_errors_rule_equals_jvp(dtype):
    """``e_R`` and ``R^T Rd v`` with either attitude's tangent a frame, both, and the
    vectors' tangents dense or zero."""
    tol = 1e-13 if dtype == jnp.float64 else 2e-5
    R, Rd = _rot(7).astype(dtype), _rot(8).astype(dtype)
    v1, v2 = _vec(9, (3,), dtype), _vec(10, (3,), dtype)
    xi, zeta = _vec(11, (3,), dtype), _vec(12, (3,), dtype)

    def fn(R, Rd, v1, v2):
        e, (a, b) = _control._errors_and_rates(R, Rd, (v1, v2))
        return [e, a, b]

    for tR, tRd in ((F.Frame(xi), None), (None, F.Frame(zeta)), (F.Frame(xi), F.Frame(zeta))):
        for tv in ((None, None), (_vec(13, (3,), dtype), None)):
            _check(fn, [R, Rd, v1, v2], [tR, tRd, *tv], tol)


def test_shape_operations_move_frames():
    """Stacks, slices, broadcasts, selects by a flag, transposes and reshapes of rotations
    keep a frame (transposes turn it into a left one); a select whose flag differs
    between entries of the matrix, and an elementwise product, take the dense tangent."""
    R, Q = _rot(14, (2,)), _rot(15)
    xi, eta = _vec(16, (2, 3)), _vec(17, (3,))

    def moves(R, Q, flag):
        S = jnp.concatenate([R, Q[None]])  # (3, 3, 3)
        T = jnp.stack([S[0], S[2]])[:, None]  # (2, 1, 3, 3)
        U = jnp.broadcast_to(T, (2, 4, 3, 3)).reshape(8, 3, 3)
        V = jnp.where(flag, U, -U).astype(jnp.float64)
        return [V, jnp.swapaxes(S, -1, -2), jnp.squeeze(S[1:2], 0)]

    tol = 1e-14
    for flag in (True, False):
        _check(moves, [R, Q, jnp.asarray(flag)], [F.Frame(xi), F.Frame(eta), None], tol, [True] * 3)
    touts = _check(moves, [R, Q, jnp.asarray(True)], [F.Frame(xi), None, None], tol, [True] * 3)
    assert touts[1].left
    # a flag that is not the same across the matrix, and a product: dense, still equal
    mask = jnp.arange(9).reshape(3, 3) % 2 == 0

    def mixed(R, Q):
        return [jnp.where(mask, R, Q), R * Q]

    _check(mixed, [R[0], Q], [F.Frame(xi[0]), F.Frame(eta)], tol, [False, False])


METHODS = [
    s.LieEuler(),
    s.RKMK4(),
    s.RKMK4(coords="cayley"),
    s.CF4(),
    s.CG3(),
    s.LGVI(),
    s.RKMK45(),
]


@pytest.mark.parametrize("method", METHODS, ids=lambda m: f"{m.name}-{getattr(m, 'coords', '')}")
def test_one_step_of_every_method(method):
    """A guarded step of the seed scene, differentiated in a gain and the state: equal to
    JAX's ``jvp``; the attitude's tangent stays three numbers through every method but
    LGVI (whose update is not a registered rule: it takes the dense tangent)."""
    scene = s.scenes.seed()
    (R0, Rd0), x0 = split_groups(scene.y0)
    dt, t0 = jnp.asarray(1e-2), jnp.asarray(0.0)

    def step(kR, R, x):
        sc = eqx.tree_at(lambda s: s.controller.gains.k_R, scene, kR)
        st = engine_step(guarded_step(sc, method, dt, t0))
        ((R1, _), x1), *_ = st((((R, Rd0), x), jnp.int32(0), jnp.int32(0), jnp.int32(-1)))
        return [R1, x1]

    R = R0 @ s.exp(jnp.array([0.3, -0.2, 0.5]))
    xs = [scene.controller.gains.k_R, R, x0]
    ts = [jnp.ones(()), F.Frame(jnp.array([0.1, 0.2, -0.3])), _vec(18, x0.shape)]
    framed = not isinstance(method, type(s.LGVI()))
    _check(step, xs, ts, 1e-13, [framed, False])


def _batched_seed_cost(method, dtype, program, seed: int, traj_cost):
    """``k -> `` the mean of ``traj_cost`` over 6-step seed runs from 16 starts (the
    scalarized Jacobian program's smallest batch), gains ``k``, in ``dtype``."""
    R0, W0 = s.initial_states(
        jax.random.PRNGKey(seed), _engine.policy.batched_layout("jacobian")[0]
    )
    sc0 = s.scenes.seed(dtype)

    def f(k):
        sc = with_gains(sc0, k[0], k[1])

        def one(R, W):
            sc1, R1 = with_start(sc, R.astype(dtype), W.astype(dtype))
            dt, t0 = jnp.asarray(0.05, dtype), jnp.asarray(0.0, dtype)
            return traj_cost(_simulate(sc1, method, dt, t0, 6, 1, program, R0=R1))

        return jnp.mean(jax.vmap(one)(R0, W0))

    return f


# (LGVI, whose rotation tangent comes out dense: tests/passes/test_pass_frames.py)
@pytest.mark.parametrize("method", [s.RKMK4(coords="cayley")], ids=str)
def test_scalarized_jacobian_with_three_number_tangents(method):
    """The scalarized one-pass Jacobian (16 runs), whose attitude tangents are three
    numbers, equals JAX's autodiff (``jacfwd`` through the gains, a cost on the saved
    points and the final state), with Cayley updates; LGVI, whose step gives a dense
    tangent, falls back to nine (the plan's ``"frames"`` entry: `so3jax.explain`)."""

    def cost(program):
        def traj(tr):
            # the saved attitudes too: their columns are three numbers, made dense after
            # the loop (from nine, converted, where LGVI's step falls back)
            saved = jnp.sum(jnp.sin(3.0 * tr.R)) + jnp.sum(tr.R * tr.Rd)
            return jnp.sum(tr.M**2) + jnp.sum(tr.extras["e_R"]) + jnp.sum(tr.y.R[0] ** 3) + saved

        return _batched_seed_cost(method, jnp.float64, program, 19, traj)

    k = jnp.array([3.0, 1.5])
    ref = jax.jit(jax.jacfwd(cost("autodiff")))(k)
    (frames,) = s.explain(jax.jacfwd(cost("auto")), k).of("frames")
    dense = isinstance(method, type(s.LGVI()))
    assert (frames["rotations"] == 0) == dense, frames  # attitude tangents of three numbers
    got = jax.jit(jax.jacfwd(cost("auto")))(k)
    assert _rel(got, ref) < 1e-10
    # (the same program with nine numbers, the pass off: tests/passes/test_pass_frames.py)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_tracking_cost_integrand_rule_equals_jvp(dtype):
    """The cost's integrand (`so3jax._tune`) at one point and at many, with the attitude's
    tangent a frame, the weights', rate's and torque's dense or zero, the reference's a
    frame, dense or zero; a left frame takes JAX's rule (dense)."""
    tol = 1e-13 if dtype == jnp.float64 else 2e-5
    for lead in ((), (4,)):
        R, Rd = _rot(20, lead).astype(dtype), _rot(21, lead).astype(dtype)
        W, M, Od = (_vec(22 + i, lead + (3,), dtype) for i in range(3))
        w = [jnp.asarray(v, dtype) for v in (1.0, 0.1, 0.01)]
        xi = _vec(25, lead + (3,), dtype)
        xs = [*w, R, W, Rd, M, Od]
        for tw, tW, tM in (
            (None, None, None),
            (jnp.asarray(0.5, dtype), _vec(26, lead + (3,), dtype), _vec(27, lead + (3,), dtype)),
        ):
            ts = [tw, None, tw, F.Frame(xi), tW, None, tM, None]
            assert not _densified(lambda *a: [_tune._integrand_of(*a)], xs, ts, tol)
        zeta, dOd = _vec(28, lead + (3,), dtype), _vec(29, lead + (3,), dtype)
        for tRd, tOd in ((F.Frame(zeta), None), (None, dOd), (F.Frame(zeta), dOd)):
            ts = [None, None, None, F.Frame(xi), None, tRd, None, tOd]
            assert not _densified(lambda *a: [_tune._integrand_of(*a)], xs, ts, tol)
        ts = [None, None, None, F.Frame(xi), None, F.Frame(zeta, left=True), None, None]
        assert _densified(lambda *a: [_tune._integrand_of(*a)], xs, ts, tol)


def _densified(fn, xs, ts, tol) -> list:
    """`_check`, and the equations that took a dense tangent for a frame."""
    F._DEBUG = []
    try:
        _check(fn, xs, ts, tol)
        return F._DEBUG
    finally:
        F._DEBUG = None


def test_scalarized_jacobian_in_float32():
    """Float32 runs (16, scalarized) carry three-number tangents too, and their ``jacfwd``
    agrees with JAX's autodiff of the float64 runs to float32's precision."""

    def cost(dtype, program):
        def traj(tr):
            return jnp.sum(tr.M**2) + jnp.sum(tr.y.R[0] ** 3) + jnp.sum(jnp.sin(3.0 * tr.R))

        return _batched_seed_cost(s.LieEuler(), dtype, program, 30, traj)

    k = jnp.array([3.0, 1.5])
    ref = jax.jit(jax.jacfwd(cost(jnp.float64, "autodiff")))(k)
    k32 = k.astype(jnp.float32)
    plan = s.explain(jax.jacfwd(cost(jnp.float32, "auto")), k32)
    assert [e["rotations"] for e in plan.of("frames")] == [1], plan
    got = jax.jit(jax.jacfwd(cost(jnp.float32, "auto")))(k32)
    assert got.dtype == jnp.float32
    assert _rel(got, ref) < 1e-4
