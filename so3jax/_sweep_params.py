"""Scene parameters a `sweep` can vary besides the gains: the plant and the task.

A sweep's ``params`` maps names to arrays whose leading axis lists values:

- ``inertia_scale``: per-axis scale ``s`` of the inertia, ``J -> D J D`` with
  ``D = diag(sqrt(s))`` (``J_ii -> s_i J_ii``), shape `(P,)` (the same on every
  axis) or `(P, 3)`; every entry > 0. The controller uses the scaled inertia
  too (it knows the plant).
- ``disturbance``: a constant body torque added to the control torque, `(P, 3)`.
- ``Omega0``: the initial body rate, `(P, 3)` (replaces the scene's ``Omega0``;
  ``omega0_std`` noise is added on top).
- ``reference_amplitude``: a factor on the reference rate and its derivative,
  `(P,)`.

With ``param_grid=True`` the named arrays are crossed (every combination);
with ``False`` they are zipped (the same ``P``: e.g. ``P`` samples drawn from
a distribution). Each combination is run from every initial attitude.

A value may also be a distribution: a function ``key -> value`` (one value, of
the shape above without ``P``). It is sampled once per initial attitude ``a``
from ``fold_in(fold_in(key, a), 2 + k)`` (``k`` the parameter's place in
`PARAMS`), so, like the attitude, sample ``a`` does not depend on the number of
attitudes, and every gain pair and grid combination sees the same draws.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._scenes import Tracking
from ._types import Array

#: The parameters a sweep can vary, with the shape of one value.
PARAMS = {
    "inertia_scale": (3,),
    "disturbance": (3,),
    "Omega0": (3,),
    "reference_amplitude": (),
}


class Disturbed(Tracking):
    """A tracking scene whose constant body disturbance torque ``d`` is required.

    ``J Omega' = M + d - Omega x J Omega``; the saved ``M`` is the control torque
    (`Tracking.disturbance`, which `prepare_scene` now sets on the scene itself).
    """

    disturbance: Array


class ScaledReference(eqx.Module):
    """A reference rate scaled by ``amplitude``: ``t -> (a Omega_d(t), a dOmega_d(t))``."""

    reference: Callable
    amplitude: Array

    def __call__(self, t):
        w, dw = self.reference(t)
        return self.amplitude * jnp.asarray(w), self.amplitude * jnp.asarray(dw)


def _validate(name: str, value, leading: str) -> np.ndarray:
    """``value`` as float64 `(n, *shape)`; ``ValueError`` naming the parameter otherwise."""
    v = np.asarray(value, dtype=np.float64)
    shape = PARAMS[name]
    if name == "inertia_scale" and v.ndim == 1:
        v = np.repeat(v[:, None], 3, axis=1)
    if v.ndim != 1 + len(shape) or v.shape[1:] != shape or v.shape[0] < 1:
        if name == "inertia_scale":
            want = f"({leading},) or ({leading}, 3)"
        else:
            want = str((leading,) + shape)
        raise ValueError(f"params[{name!r}] must have shape {want}, got {np.shape(value)}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"params[{name!r}] must be finite")
    if name == "inertia_scale" and np.any(v <= 0):
        raise ValueError(
            f"params['inertia_scale'] must be > 0 (a scale of the inertia), got min {v.min():g}"
        )
    return v


def split_params(params: Mapping | None) -> tuple[dict, dict]:
    """``(arrays, distributions)``: names checked, callables set apart."""
    if params is None:
        return {}, {}
    if not isinstance(params, Mapping):
        raise TypeError(f"params must be a mapping of names to arrays, got {type(params).__name__}")
    arrays, dists = {}, {}
    for name, value in params.items():
        if name not in PARAMS:
            raise ValueError(f"params: unknown parameter {name!r}; choose from {', '.join(PARAMS)}")
        (dists if callable(value) else arrays)[name] = value
    return arrays, dists


def draw(dists: Mapping[str, Callable], key, n: int) -> dict[str, np.ndarray]:
    """Sample each distribution once per attitude ``a < n``; name -> `(n, *shape)`."""
    out = {}
    for name, f in dists.items():
        k = list(PARAMS).index(name)
        keys = jax.vmap(lambda a, k=k: jax.random.fold_in(jax.random.fold_in(key, a), 2 + k))(
            jnp.arange(n)
        )
        try:
            v = jax.vmap(f)(keys)
        except Exception as e:
            raise ValueError(
                f"params[{name!r}]: a distribution must be a function key -> value; it failed: {e}"
            ) from e
        shape = PARAMS[name]
        if name == "inertia_scale" and np.shape(v) == (n,):
            v = np.repeat(np.asarray(v)[:, None], 3, axis=1)
        if np.shape(v) != (n,) + shape:
            raise ValueError(
                f"params[{name!r}]: a distribution must return one value of shape {shape}, "
                f"got {np.shape(v)[1:]}"
            )
        out[name] = _validate(name, v, "n_attitudes")
    return out


def check_params(params: Mapping | None, grid: bool) -> dict[str, np.ndarray]:
    """Validate the arrays of ``params``; return one row per combination, name -> `(P, ...)`."""
    if not params:
        return {}
    out = {name: _validate(name, value, "P") for name, value in params.items()}
    sizes = {k: v.shape[0] for k, v in out.items()}
    if grid:
        idx = np.meshgrid(*[np.arange(n) for n in sizes.values()], indexing="ij")
        return {k: out[k][i.reshape(-1)] for k, i in zip(out, idx, strict=True)}
    if len(set(sizes.values())) > 1:
        raise ValueError(
            "with param_grid=False the parameters are zipped and need the same length, got "
            + ", ".join(f"{k}: {n}" for k, n in sizes.items())
        )
    return out


def prepare_scene(scene: Tracking, names) -> Tracking:
    """The scene with the slots the named parameters need (a disturbance, a scaled reference)."""
    dtype = scene.y0.R.dtype
    if "disturbance" in names and scene.disturbance is None:
        # A slot on the scene itself: its torque limit and control period stay.
        scene = eqx.tree_at(
            lambda s: s.disturbance, scene, jnp.zeros(3, dtype), is_leaf=lambda a: a is None
        )
    if "reference_amplitude" in names:
        scene = eqx.tree_at(
            lambda s: s.reference, scene, ScaledReference(scene.reference, jnp.ones((), dtype))
        )
    return scene


def apply_params(scene: Tracking, values: Mapping[str, Array]) -> Tracking:
    """The scene with one value of each parameter (traceable: works under `vmap`).

    ``Omega0`` is applied by the caller (it is part of the initial state).
    """
    dtype = scene.y0.R.dtype
    if "inertia_scale" in values:
        d = jnp.sqrt(jnp.asarray(values["inertia_scale"], dtype))
        J, Jinv = scene.body.inertia, scene.body.inertia_inv
        scene = eqx.tree_at(
            lambda s: (s.body.inertia, s.body.inertia_inv),
            scene,
            (d[:, None] * J * d[None, :], Jinv / (d[:, None] * d[None, :])),
        )
    if "disturbance" in values:
        scene = eqx.tree_at(
            lambda s: s.disturbance, scene, jnp.asarray(values["disturbance"], dtype)
        )
    if "reference_amplitude" in values:
        scene = eqx.tree_at(
            lambda s: s.reference.amplitude,
            scene,
            jnp.asarray(values["reference_amplitude"], dtype),
        )
    return scene
