"""SO(3) primitives under transformations: gradients (float64 and float32), vmap, batching."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.spatial.transform import Rotation

import so3jax

F64, F32 = np.float64, np.float32
PI_MARGIN = 1e-3  # "near pi" for functions of R, whose log flips sign at pi


def unit_vectors(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def grad_points(seed, near_pi_margin=1e-9, tiny=True):
    """Rotation vectors: 3 uniform, (3 of size ~1e-6), 3 within ``near_pi_margin`` of pi."""
    rng = np.random.default_rng(seed)
    pts = [Rotation.random(3, random_state=rng).as_rotvec()]
    if tiny:
        pts.append(1e-6 * rng.normal(size=(3, 3)))
    pts.append(unit_vectors(rng, 3) * (np.pi - near_pi_margin))
    return np.concatenate(pts)


def rot_pi(u):
    u = np.asarray(u, float)
    return 2.0 * np.outer(u, u) - np.eye(3)


def weighted_sum(x, seed=0):
    """A scalar function of every entry of a pytree, with fixed random weights."""
    leaves = jax.tree.leaves(x)
    rng = np.random.default_rng(seed)
    return sum(jnp.sum(jnp.sin(l * rng.normal(size=l.shape).astype(l.dtype))) for l in leaves)


# --------------------------------------------------------------------------
# check_grads (float64): fwd and rev mode against finite differences
# --------------------------------------------------------------------------

# check_grads' finite differences with step 1e-6 are good to ~1e-9 here.
GRAD_TOL = dict(eps=1e-6, atol=1e-6, rtol=1e-6)

W_POINTS = grad_points(0)
R_POINTS = Rotation.from_rotvec(grad_points(1, PI_MARGIN)).as_matrix()
R_POINTS_NO_TINY = Rotation.from_rotvec(grad_points(2, PI_MARGIN, tiny=False)).as_matrix()


def _jacobians(w):
    return (
        so3jax.left_jacobian(w),
        so3jax.right_jacobian(w),
        so3jax.left_jacobian_inv(w),
        so3jax.right_jacobian_inv(w),
    )


CHECK_GRADS = [
    # (name, function, arguments, order, modes); related functions share a check
    # (and a compilation) by returning a tuple.
    ("exp", so3jax.exp, (W_POINTS,), 1, ("fwd", "rev")),
    ("exp_order2", so3jax.exp, (W_POINTS,), 2, ("fwd",)),
    ("jacobians", _jacobians, (W_POINTS,), 1, ("fwd", "rev")),
    ("log_to_quat", lambda R: (so3jax.log(R), so3jax.to_quat(R)), (R_POINTS,), 1, ("fwd", "rev")),
    (
        "from_quat",
        so3jax.from_quat,
        (np.random.default_rng(3).normal(size=(9, 4)),),
        1,
        ("fwd", "rev"),
    ),
    (
        "project",
        so3jax.project,
        (R_POINTS + 0.1 * np.random.default_rng(4).normal(size=(9, 3, 3)),),
        1,
        ("fwd", "rev"),
    ),
    # the geodesic distance is |w|-like at 0: no tiny angles
    (
        "distances",
        lambda R, S: (so3jax.geodesic_distance(R, S), so3jax.attitude_error_function(R, S)),
        (R_POINTS_NO_TINY, R_POINTS_NO_TINY[::-1]),
        1,
        ("fwd", "rev"),
    ),
]


@pytest.mark.parametrize(
    "fn, args, order, modes", [c[1:] for c in CHECK_GRADS], ids=[c[0] for c in CHECK_GRADS]
)
def test_check_grads(fn, args, order, modes):
    check_grads(jax.jit(fn), args, order=order, modes=modes, **GRAD_TOL)


# --------------------------------------------------------------------------
# Exactly at theta = 0 and theta = pi: finite (and right) derivatives, both dtypes
# --------------------------------------------------------------------------

DTYPES = [F64, F32]
SPECIAL_W = {
    "zero": np.zeros(3),
    "pi_e1": np.array([np.pi, 0.0, 0.0]),
    "pi_random": np.pi * np.array([0.48, -0.6, 0.64]),
}
SPECIAL_R = {
    "identity": np.eye(3),
    "pi_e1": rot_pi([1.0, 0.0, 0.0]),  # diag(1, -1, -1)
    "pi_e3": rot_pi([0.0, 0.0, 1.0]),
    "pi_random": rot_pi([0.48, -0.6, 0.64]),
}


def _eye(x):
    return jnp.eye(3, dtype=x.dtype)


# (left_jacobian_inv and right_jacobian share their code with the two below)
FUNCTIONS_OF_W = {
    "exp": so3jax.exp,
    "left_jacobian": so3jax.left_jacobian,
    "right_jacobian_inv": so3jax.right_jacobian_inv,
}
FUNCTIONS_OF_R = {
    "log": so3jax.log,
    "to_quat": so3jax.to_quat,
    "geodesic_distance": lambda R: so3jax.geodesic_distance(R, _eye(R)),
    "attitude_error_function": lambda R: so3jax.attitude_error_function(R, _eye(R)),
}


def _derivatives(functions, forward):
    """Reverse-mode gradients of every function (and forward-mode Jacobians of some),
    vmapped over points: one compilation per dtype."""

    def derivs(x):
        out = {}
        for name, f in functions.items():
            out[name] = jax.grad(lambda x, f=f: weighted_sum(f(x)))(x)
        for name in forward:
            out[name + " (fwd)"] = jax.jacfwd(functions[name])(x)
        return out

    return jax.jit(jax.vmap(derivs))


_derivatives_of_w = _derivatives(FUNCTIONS_OF_W, forward=["exp"])
_derivatives_of_r = _derivatives(FUNCTIONS_OF_R, forward=["log"])


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize(
    "points, derivatives",
    [(SPECIAL_W, _derivatives_of_w), (SPECIAL_R, _derivatives_of_r)],
    ids=["w", "R"],
)
def test_derivatives_finite_at_zero_and_pi(points, derivatives, dtype):
    x = jnp.asarray(np.stack(list(points.values())), dtype)
    for name, d in derivatives(x).items():
        assert d.dtype == dtype
        finite = np.isfinite(np.asarray(d)).reshape(len(points), -1).all(-1)
        bad = [p for p, ok in zip(points, finite, strict=True) if not ok]
        assert not bad, f"d {name} is not finite at {bad}"


@jax.jit
def _jvps_at_identity(v, E):
    zero, eye = jnp.zeros_like(v), jnp.eye(3, dtype=v.dtype)
    return {
        "exp": jax.jvp(so3jax.exp, (zero,), (v,))[1],
        "log": jax.jvp(so3jax.log, (eye,), (E,))[1],
        "project": jax.jvp(so3jax.project, (eye,), (E,))[1],
        "project (rev)": jax.grad(lambda M: jnp.sum(E * so3jax.project(M)))(eye),
        "left_jacobian": jax.jvp(so3jax.left_jacobian, (zero,), (v,))[1],
        "left_jacobian_inv": jax.jvp(so3jax.left_jacobian_inv, (zero,), (v,))[1],
        "J(0)": [so3jax.right_jacobian(zero), so3jax.right_jacobian_inv(zero)],
    }


@pytest.mark.parametrize("dtype", DTYPES)
def test_derivatives_at_identity_are_right(dtype):
    """d exp(t v)/dt = hat(v); d log(I + t E)/dt = vee(skew E); d project(I + t E)/dt = skew E
    (forward and reverse mode); J(0) = I; d J_l(t v)/dt = hat(v) / 2 = -d J_l^-1(t v)/dt."""
    rng = np.random.default_rng(5)
    v = rng.normal(size=3).astype(dtype)
    E = rng.normal(size=(3, 3)).astype(dtype)
    V, skew = so3jax.hat(v), 0.5 * (E - E.T)
    expected = {
        "exp": V,
        "log": so3jax.vee(skew),
        "project": skew,
        "project (rev)": skew,  # d/dM <E, project(M)> at I is the skew part of E
        "left_jacobian": 0.5 * V,
        "left_jacobian_inv": -0.5 * V,
        "J(0)": [np.eye(3), np.eye(3)],
    }
    got = _jvps_at_identity(v, E)
    for name in expected:
        for a, b in zip(jax.tree.leaves(got[name]), jax.tree.leaves(expected[name]), strict=True):
            assert a.dtype == dtype
            np.testing.assert_allclose(a, b, atol=10 * np.finfo(dtype).eps, err_msg=name)


def test_float32_derivatives_match_float64():
    """The same derivatives as above (same compilations) at random points."""
    rng = np.random.default_rng(6)
    w = np.concatenate([Rotation.random(2, random_state=rng).as_rotvec(), [[0.0, 3.0, 0.5]]])
    R = Rotation.random(len(SPECIAL_R), random_state=rng).as_matrix()
    for derivatives, x in ((_derivatives_of_w, w), (_derivatives_of_r, R)):
        d64, d32 = derivatives(jnp.asarray(x)), derivatives(jnp.asarray(x, F32))
        for name in d64:
            assert d32[name].dtype == F32
            scale = float(jnp.abs(d64[name]).max())
            np.testing.assert_allclose(d32[name], d64[name], atol=1e-5 * scale, err_msg=name)


# --------------------------------------------------------------------------
# Batching: shapes (), (1,), (3, 1, 2); vmap(f)(x)[i] == f(x[i])
# --------------------------------------------------------------------------


def make_inputs(batch, seed=0):
    """One of each kind of argument, with leading shape ``batch``."""
    rng = np.random.default_rng(seed)
    n = int(np.prod(batch))

    def rots():
        return Rotation.random(n, random_state=rng).as_matrix().reshape(batch + (3, 3))

    M = rots() + 0.2 * rng.normal(size=batch + (3, 3))
    M = np.where((np.linalg.det(M) > 0)[..., None, None], M, -M)
    return {
        "a": rng.normal(size=batch + (3,)),
        "b": rng.normal(size=batch + (3,)),
        "R": rots(),
        "S": rots(),
        "M": M,
        "p": rng.normal(size=batch + (4,)),
        "q": rng.normal(size=batch + (4,)),
        "x": rng.uniform(-3, 3, size=batch),
        "y": rng.uniform(-1.5, 1.5, size=batch),
        "z": rng.uniform(-3, 3, size=batch),
    }


# name -> (function of the inputs, trailing shape of each output)
PRIMITIVES = {
    "hat": (lambda d: so3jax.hat(d["a"]), [(3, 3)]),
    "vee": (lambda d: so3jax.vee(d["M"]), [(3,)]),
    "bracket": (lambda d: so3jax.bracket(d["a"], d["b"]), [(3,)]),
    "adjoint": (lambda d: so3jax.adjoint(d["R"], d["a"]), [(3,)]),
    "coadjoint": (lambda d: so3jax.coadjoint(d["R"], d["b"]), [(3,)]),
    "exp": (lambda d: so3jax.exp(d["a"]), [(3, 3)]),
    "log": (lambda d: so3jax.log(d["R"]), [(3,)]),
    "left_jacobian": (lambda d: so3jax.left_jacobian(d["a"]), [(3, 3)]),
    "left_jacobian_inv": (lambda d: so3jax.left_jacobian_inv(d["a"]), [(3, 3)]),
    "right_jacobian": (lambda d: so3jax.right_jacobian(d["a"]), [(3, 3)]),
    "right_jacobian_inv": (lambda d: so3jax.right_jacobian_inv(d["a"]), [(3, 3)]),
    "from_quat": (lambda d: so3jax.from_quat(d["p"]), [(3, 3)]),
    "to_quat": (lambda d: so3jax.to_quat(d["R"]), [(4,)]),
    "quat_multiply": (lambda d: so3jax.quat_multiply(d["p"], d["q"]), [(4,)]),
    "from_axis_angle": (lambda d: so3jax.from_axis_angle(d["a"], d["x"]), [(3, 3)]),
    "to_axis_angle": (lambda d: so3jax.to_axis_angle(d["R"]), [(3,), ()]),
    "from_euler_zyx": (lambda d: so3jax.from_euler_zyx(d["x"], d["y"], d["z"]), [(3, 3)]),
    "to_euler_zyx": (lambda d: so3jax.to_euler_zyx(d["R"]), [(), (), ()]),
    "euler_zyx_rate_matrix": (
        lambda d: so3jax.euler_zyx_rate_matrix(d["x"], d["y"], d["z"]),
        [(3, 3)],
    ),
    "is_gimbal_locked": (lambda d: so3jax.is_gimbal_locked(d["R"], atol=0.5), [()]),
    "project": (lambda d: so3jax.project(d["M"]), [(3, 3)]),
    "geodesic_distance": (lambda d: so3jax.geodesic_distance(d["R"], d["S"]), [()]),
    "attitude_error_function": (lambda d: so3jax.attitude_error_function(d["R"], d["S"]), [()]),
    "orthogonality_error": (lambda d: so3jax.orthogonality_error(d["M"]), [()]),
}


@jax.jit
def all_primitives(d):
    return {name: f(d) for name, (f, _) in PRIMITIVES.items()}


BATCHES = [(), (1,), (3, 1, 2)]
BIG = BATCHES[-1]


def _index(tree, idx):
    return jax.tree.map(lambda x: x[idx], tree)


@pytest.fixture(scope="module")
def shapes():
    """Output shapes of every primitive for each batch shape (traced, not compiled)."""
    return {batch: jax.eval_shape(all_primitives, make_inputs(batch)) for batch in BATCHES}


@pytest.fixture(scope="module")
def batched():
    """Every primitive on a (3, 1, 2) batch, on each element alone, and vmapped over all 6."""
    d = make_inputs(BIG)
    singles = {idx: all_primitives(_index(d, idx)) for idx in np.ndindex(*BIG)}
    flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[len(BIG) :]), d)
    return all_primitives(d), singles, jax.jit(jax.vmap(all_primitives))(flat)


def _assert_same(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        assert x.shape == y.shape and x.dtype == y.dtype
        np.testing.assert_allclose(x, y, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("name", list(PRIMITIVES))
def test_batch_shapes(name, shapes):
    for batch in BATCHES:
        leaves = jax.tree.leaves(shapes[batch][name])
        got = [leaf.shape for leaf in leaves]
        assert got == [batch + t for t in PRIMITIVES[name][1]], (batch, got)
        assert all(leaf.dtype in (jnp.float64, jnp.bool_) for leaf in leaves)


@pytest.mark.parametrize("name", list(PRIMITIVES))
def test_batched_call_matches_per_element_calls(name, batched):
    out, singles, _ = batched
    for idx, single in singles.items():
        _assert_same(_index(out[name], idx), single[name])


@pytest.mark.parametrize("name", list(PRIMITIVES))
def test_vmap_matches_per_element_calls(name, batched):
    _, singles, vmapped = batched
    for k, single in enumerate(singles.values()):
        _assert_same(_index(vmapped[name], k), single[name])


def test_broadcasting_between_arguments():
    rng = np.random.default_rng(8)
    R = Rotation.random(6, random_state=rng).as_matrix().reshape(3, 1, 2, 3, 3)
    S = Rotation.random(2, random_state=rng).as_matrix()
    a = rng.normal(size=(2, 3))

    def shape(f, *args):  # traced, not compiled
        return jax.eval_shape(f, *args).shape

    assert shape(so3jax.geodesic_distance, R, S) == (3, 1, 2)
    assert shape(so3jax.attitude_error_function, R, S) == (3, 1, 2)
    assert shape(so3jax.adjoint, R, a) == (3, 1, 2, 3)
    assert shape(so3jax.from_axis_angle, a, np.ones((4, 1))) == (4, 2, 3, 3)
    assert shape(so3jax.from_euler_zyx, np.ones((3, 1)), 0.5, np.ones(2)) == (3, 2, 3, 3)
    assert shape(so3jax.euler_zyx_rate_matrix, np.ones((3, 1)), 0.5, np.ones(2)) == (3, 2, 3, 3)
    ref = (Rotation.from_matrix(R.reshape(3, 2, 3, 3)).inv() * Rotation.from_matrix(S)).magnitude()
    got = jax.jit(so3jax.geodesic_distance)(R, S)
    np.testing.assert_allclose(got[:, 0], ref.reshape(3, 2), atol=1e-14)


def test_random_rotation_vmap_over_keys():
    keys = jax.random.split(jax.random.key(0), 4)
    sample = jax.jit(so3jax.random_rotation, static_argnames=("shape", "dtype"))
    batched = jax.vmap(lambda k: sample(k, (2,)))(keys)
    assert batched.shape == (4, 2, 3, 3)
    for i in range(4):
        np.testing.assert_array_equal(batched[i], sample(keys[i], (2,)))


# --------------------------------------------------------------------------
# closed-form derivatives of the integrators' group updates
# --------------------------------------------------------------------------


def _increment_pairs():
    from so3jax import _so3 as S, _updates as U

    return {
        "exp_increment": (U._exp_increment, lambda R, w: S._mm(R, S._expm1_raw(w))),
        "expm1": (lambda R, w: S._mm(R, U._expm1(w)), lambda R, w: S._mm(R, S._expm1_raw(w))),
        "cay_increment": (U._cay_increment, S._cay_increment_raw),
        "exp_update": (U._exp_update, lambda R, w: R + S._mm(R, S._expm1_raw(w))),
        "cay_update": (U._cay_update, lambda R, u: R + S._cay_increment_raw(R, u)),
    }


@pytest.mark.parametrize(
    "name", ["exp_increment", "expm1", "cay_increment", "exp_update", "cay_update"]
)
@pytest.mark.parametrize("dtype", [F64, F32])
def test_group_update_derivatives_match_autodiff(name, dtype):
    """The hand-written jvp rules equal autodiff of the plain formulas, at every angle.

    Angles 0, 1e-9 (the series branch), moderate, near pi and past it; both
    tangents together and each alone (symbolic zeros); reverse mode; and in
    float64 second order (Hessian-vector products). One compiled program per
    case keeps the test cheap.
    """
    closed, plain = _increment_pairs()[name]
    rng = np.random.default_rng(3)
    n = 7
    w = unit_vectors(rng, n) * np.array([0.0, 1e-9, 1e-4, 0.3, 1.7, np.pi - 1e-6, 5.0])[:, None]
    R = rng.normal(size=(n, 3, 3))
    dR, dw, v = rng.normal(size=(n, 3, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, 12))
    R, w, dR, dw, v = (jnp.asarray(x, dtype) for x in (R, w, dR, dw, v))
    second_order = dtype == F64

    def checks(f):
        out = [
            jax.jvp(f, (R, w), (dR, dw)),
            jax.jvp(lambda R: f(R, w), (R,), (dR,)),  # the w tangent a symbolic zero
            jax.jvp(lambda w: f(R, w), (w,), (dw,)),  # the R tangent a symbolic zero
        ]

        def scalar(x):
            return weighted_sum(f(x[:, 3:].reshape(n, 3, 3), x[:, :3]))

        x = jnp.concatenate([w, R.reshape(n, 9)], axis=1)
        out.append(jax.grad(scalar)(x))
        if second_order:
            out.append(jax.jvp(jax.grad(scalar), (x,), (v,))[1])
        return out

    got, want = jax.jit(lambda: (checks(closed), checks(plain)))()
    tol = dict(rtol=1e-12, atol=1e-12) if dtype == F64 else dict(rtol=2e-5, atol=2e-5)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        assert a.dtype == dtype
        np.testing.assert_allclose(a, b, **tol)


def test_group_update_derivative_matches_finite_differences():
    """The rules against central differences (not only against autodiff of the same formula)."""
    from so3jax import _updates as U

    rng = np.random.default_rng(4)
    R = jnp.asarray(Rotation.random(random_state=rng).as_matrix())
    dR = jnp.asarray(rng.normal(size=(3, 3)))
    for w in (np.zeros(3), rng.normal(size=3), unit_vectors(rng, 1)[0] * (np.pi - 1e-3)):
        dw = rng.normal(size=3)
        for f in (U._exp_increment, U._cay_increment, U._exp_update, U._cay_update):
            _, t = jax.jvp(f, (R, jnp.asarray(w)), (dR, jnp.asarray(dw)))
            eps = 1e-6
            fd = (f(R + eps * dR, w + eps * dw) - f(R - eps * dR, w - eps * dw)) / (2 * eps)
            np.testing.assert_allclose(t, fd, atol=1e-8)


@pytest.mark.parametrize("coords", ["exp", "cayley"])
def test_step_end_derivative_matches_autodiff(coords):
    """`_state.advance` (the end of an RKMK step: the update's rule beside ``x + dx``)
    equals autodiff of the plain formulas: all tangents, only the vector part's (the
    group's a symbolic zero), only the group's, reverse mode and second order."""
    from so3jax import _so3 as S, _state

    raw = S._cay_increment_raw if coords == "cayley" else (lambda R, w: S._mm(R, S._expm1_raw(w)))
    rng = np.random.default_rng(5)
    n = 4
    R = jnp.asarray(Rotation.random(n, random_state=rng).as_matrix())[:, None]  # k = 1 group
    u = jnp.asarray(unit_vectors(rng, n) * np.array([0.0, 1e-9, 0.4, 2.5])[:, None])[:, None]
    x, dx = jnp.asarray(rng.normal(size=(n, 3))), jnp.asarray(rng.normal(size=(n, 3)))
    t = [jnp.asarray(rng.normal(size=a.shape)) for a in (R, u, x, dx)]

    def closed(R, u, x, dx):
        y = _state.advance(_state.LieState(R, x), u, dx, coords)
        return y.R, y.x

    def plain(R, u, x, dx):
        return R + raw(R, u), x + dx

    def checks(f):
        out = [
            jax.jvp(f, (R, u, x, dx), tuple(t)),
            jax.jvp(lambda x, dx: f(R, u, x, dx), (x, dx), (t[2], t[3])),
            jax.jvp(lambda R, u: f(R, u, x, dx), (R, u), (t[0], t[1])),
        ]

        def scalar(R, u, x, dx):
            a, b = f(R, u, x, dx)
            return weighted_sum(a) + weighted_sum(b, seed=1)

        out.append(jax.grad(scalar, argnums=(0, 1, 2, 3))(R, u, x, dx))
        g = jax.grad(scalar, argnums=(0, 1))
        out.append(jax.jvp(lambda R, u: g(R, u, x, dx), (R, u), (t[0], t[1]))[1])
        return out

    got, want = jax.jit(lambda: (checks(closed), checks(plain)))()
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
