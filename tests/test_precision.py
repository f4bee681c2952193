"""Every contraction so3jax writes asks for full precision, on every backend.

In float32 on a GPU, JAX's default precision for a ``dot_general`` is TF32 (a 10-bit
mantissa, about 5e-4 relative), which breaks the float32 agreement the passes are proved to
(1e-5) and would flag a rotation valid in float32 as not one (`rotation_tolerance`). A CPU
computes every precision alike, so the invariant is checked where it is written: each
``dot_general`` in the programs of a run and its derivatives carries
``Precision.HIGHEST``. The equality of the programs with the reference, in float32, is
`tests/passes`'s.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import pytest

import so3jax as s
from so3jax._tune import with_gains


def _dot_precisions(jaxpr, found: list) -> list:
    """The ``precision`` of every ``dot_general`` in ``jaxpr`` and the programs inside it."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            found.append(eqn.params["precision"])
        for value in eqn.params.values():
            for v in value if isinstance(value, (list, tuple)) else (value,):
                inner = getattr(v, "jaxpr", v)  # a closed program or a program
                if hasattr(inner, "eqns"):
                    _dot_precisions(inner, found)
    return found


def _seed_cost(method):
    seed = s.scenes.seed()

    def cost(k):
        tr = s.simulate(with_gains(seed, k[0], k[1]), method, 0.01, 20)
        return jnp.sum(tr.Omega**2) + s.tracking_cost(tr, seed)

    return cost, jnp.array([8.81, 2.54])


def _mean_cost():
    R0, W0 = s.initial_states(jax.random.key(1), 16)

    def cost(k):
        return s.expected_cost(s.scenes.seed(), k[0], k[1], R0, W0, s.RKMK4(), 1e-2, 20)

    return cost, jnp.array([8.81, 2.54])


def _quadrotor_cost():
    quad = s.scenes.quadrotor_circle(control_period=0.0025)

    def cost(g):
        sc = eqx.tree_at(lambda q: q.gains, quad, g)
        return jnp.sum(s.simulate(sc, s.RKMK4(), 0.0025, 20).extras["e_x"] ** 2)

    return cost, quad.gains


CASES = {
    "seed RKMK4": lambda: _seed_cost(s.RKMK4()),
    "seed CF4": lambda: _seed_cost(s.CF4()),
    "seed LGVI": lambda: _seed_cost(s.LGVI()),
    "mean cost": _mean_cost,
    "quadrotor": _quadrotor_cost,
}
TRANSFORMS = {
    "jit": lambda f: f,
    "grad": jax.grad,
    "jacfwd": jax.jacfwd,
    "vmap of grad": lambda f: jax.vmap(jax.grad(f)),
    "hessian": jax.hessian,
}


#: Each case under the transforms that reach a contraction of its own: the forward pass
#: (the rotation check of the input), a first derivative by each strategy and mode, and a
#: second derivative once.
PAIRS = [
    *((c, t) for c in CASES for t in ("jit", "grad")),
    ("seed RKMK4", "jacfwd"),
    ("seed RKMK4", "hessian"),
    ("mean cost", "jacfwd"),
    ("mean cost", "vmap of grad"),
    ("quadrotor", "vmap of grad"),
]


@pytest.mark.parametrize(("case", "transform"), PAIRS)
def test_every_contraction_asks_for_full_precision(case, transform):
    cost, x = CASES[case]()
    if transform.startswith("vmap"):
        x = jax.tree.map(lambda a: jnp.stack([a, 1.01 * a]), x)
    found = _dot_precisions(jax.make_jaxpr(TRANSFORMS[transform](cost))(x).jaxpr, [])
    highest = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)
    assert found, "no contraction found: the program walked is not the one that runs"
    assert all(p == highest for p in found), found
