"""so3jax's own ``linear_call`` primitive (`so3jax._engine.linear_call`): the contract of
`jax.custom_derivatives.linear_call` (a linear map whose transpose is the function given),
plus batching. Checked on a map with a known transpose: ``f(r, x) = r * (A @ x)``."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from so3jax._engine.linear_call import AVAILABLE, linear_call

pytestmark = pytest.mark.skipif(not AVAILABLE, reason="JAX lacks the rule tables")

A = jnp.asarray(np.random.default_rng(0).normal(size=(3, 4)))


def f(r, x):
    return r * (A @ x)


def f_transpose(r, ct):
    return r * (A.T @ ct)


def marked_transpose(r, ct):  # a transpose JAX could not have derived: twice the true one
    return 2.0 * f_transpose(r, ct)


def call(r, x, transpose=f_transpose):
    return linear_call(f, transpose, r, x)


def test_value_jvp_and_transpose():
    r, x, dx = 1.5, jnp.arange(4.0), jnp.ones(4)
    np.testing.assert_allclose(call(r, x), f(r, x))
    y, dy = jax.jvp(lambda x: call(r, x), (x,), (dx,))
    np.testing.assert_allclose(dy, f(r, dx))  # linear: the tangent is the map of dx
    ct = jnp.arange(3.0)
    (g,) = jax.vjp(lambda x: call(r, x, marked_transpose), x)[1](ct)
    np.testing.assert_allclose(g, 2.0 * f_transpose(r, ct))  # the given transpose runs
    (g,) = jax.vjp(lambda x: call(r, x), x)[1](ct)
    np.testing.assert_allclose(g, jax.vjp(lambda x: f(r, x), x)[1](ct)[0])


def test_transpose_of_the_transpose_is_the_map():
    r, x, ct = 0.5, jnp.arange(4.0), jnp.arange(3.0)

    def back(ct):
        return jax.vjp(lambda x: call(r, x), x)[1](ct)[0]

    (again,) = jax.vjp(back, ct)[1](x)  # transposing the transpose: the original map
    np.testing.assert_allclose(again, f(r, x))


def test_batching_equals_a_loop():
    rs = jnp.array([1.0, 2.0, 3.0])
    xs = jnp.arange(12.0).reshape(3, 4)
    cts = jnp.arange(9.0).reshape(3, 3)

    def grad_of(r, x, ct):
        return jax.vjp(lambda x: call(r, x), x)[1](ct)[0]

    batched = jax.jit(jax.vmap(grad_of))(rs, xs, cts)
    loop = jnp.stack([grad_of(rs[i], xs[i], cts[i]) for i in range(3)])
    np.testing.assert_allclose(batched, loop)
    # a batched residual with an unbatched linear input, and the batch on another axis
    out = jax.vmap(lambda r: call(r, xs[0]))(rs)
    np.testing.assert_allclose(out, jnp.stack([f(r, xs[0]) for r in rs]))
    out = jax.vmap(lambda x: call(2.0, x), in_axes=1, out_axes=1)(xs.T)
    np.testing.assert_allclose(out, jnp.stack([f(2.0, x) for x in xs], axis=1))


def test_closed_over_values_are_operands():
    """The map may close over a traced value of the caller's trace (it becomes an operand);
    the transpose, traced later, takes what it needs from the residuals (as with JAX's
    ``linear_call``)."""

    @jax.jit
    def g(s, x):
        return linear_call(
            lambda r, x: s * f(r[0], x), lambda r, ct: r[1] * f_transpose(r[0], ct), (1.0, s), x
        )

    np.testing.assert_allclose(g(3.0, jnp.ones(4)), 3.0 * f(1.0, jnp.ones(4)))
    grad = jax.grad(lambda x: jnp.sum(g(3.0, x)))(jnp.ones(4))
    np.testing.assert_allclose(grad, 3.0 * f_transpose(1.0, jnp.ones(3)))


def test_a_map_with_its_output_shapes_is_traced_only_where_it_is_evaluated():
    """With ``out_shapes`` the map is traced where the call is evaluated (forward mode, a
    batch of values), never under reverse mode alone, which needs only the transpose; the
    results are those of the call without it. A wrong shape, or a map that closes over a
    traced value, raises a ValueError naming the contract."""
    traced = []

    def fun(r, x):
        traced.append(1)
        return f(r, x)

    shapes = jax.ShapeDtypeStruct((3,), jnp.float64)

    def lazy(r, x, fun=fun, shapes=shapes):
        return linear_call(fun, f_transpose, r, x, out_shapes=shapes)

    r, x, ct = 1.5, jnp.arange(4.0), jnp.arange(3.0)
    (g,) = jax.jit(lambda x: jax.vjp(lambda x: lazy(r, x), x)[1](ct))(x)
    np.testing.assert_allclose(g, f_transpose(r, ct))
    rs, xs = jnp.array([1.0, 2.0]), jnp.stack([x, 2 * x])
    batched = jax.jit(jax.vmap(lambda r, x: jax.grad(lambda x: lazy(r, x) @ ct)(x)))(rs, xs)
    np.testing.assert_allclose(batched, jnp.stack([f_transpose(1.0, ct), f_transpose(2.0, ct)]))
    assert not traced  # reverse mode, batched or not, never traced the map
    np.testing.assert_allclose(jax.jit(lambda x: lazy(r, x))(x), f(r, x))
    _, dy = jax.jvp(lambda x: lazy(r, x), (x,), (jnp.ones(4),))
    np.testing.assert_allclose(dy, f(r, jnp.ones(4)))
    np.testing.assert_allclose(jax.vmap(lazy)(rs, xs), jax.vmap(f)(rs, xs))
    assert traced
    with pytest.raises(ValueError, match="out_shapes"):
        lazy(r, x, shapes=jax.ShapeDtypeStruct((4,), jnp.float64))
    with pytest.raises(ValueError, match="traced value"):
        jax.jit(lambda s, x: lazy(r, x, fun=lambda r, x: s * f(r, x)))(2.0, x)
