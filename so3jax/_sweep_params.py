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
- ``max_torque``: the actuators' torque limit in N m per body axis, `(P,)` (the same
  on every axis) or `(P, 3)`, every entry > 0 (`scenes.tracking`'s ``max_torque``).
- ``noise_scale``: a factor ``c >= 0`` on every standard deviation of the scene's
  `SensorNoise` (``sigma -> c sigma``), `(P,)`; a scene built with ``noise`` (attitude
  scenes and quadrotors alike). ``c = 0`` is the noise-free run (to round-off).

A quadrotor (`prepare_quadrotor`, `apply_quadrotor_params`) takes ``Omega0`` and

- ``thrust_max``: each rotor's thrust limit in N, `(P,)` (a scene built with
  ``rotors``); or ``thrust_to_weight``, ``4 thrust_max / (m g)``, `(P,)` (not both);
  either must let the rotors hover (``4 thrust_max >= m g``) and stay above the
  rotors' ``thrust_min``.
- ``time_constant``: the rotor lag ``tau`` in s, `(P,)`, > 0 (a scene whose rotors
  have a time constant, so that their thrusts are state).
- ``wind_speed``: a constant mean wind in m/s, world frame, `(P, 3)` (a scene with
  ``drag``).
- ``noise_scale``, as for an attitude scene.

Which parameters a scene takes is its sweep hook's (`so3jax._sweep_hooks`).

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
    # New names go at the end: a distribution's draws are keyed by the place here.
    "max_torque": (3,),
    "thrust_max": (),
    "thrust_to_weight": (),
    "time_constant": (),
    "wind_speed": (3,),
    "noise_scale": (),
}

#: What each parameter is, and its unit ("" for a pure number): axis labels of plots.
PARAM_LABELS = {
    "inertia_scale": ("inertia scale", ""),
    "disturbance": ("disturbance torque", "N m"),
    "Omega0": ("initial rate", "rad/s"),
    "reference_amplitude": ("reference amplitude", ""),
    "max_torque": ("torque limit", "N m"),
    "thrust_max": ("rotor thrust limit", "N"),
    "thrust_to_weight": ("thrust-to-weight ratio 4 thrust_max / (m g)", ""),
    "time_constant": ("rotor time constant", "s"),
    "wind_speed": ("mean wind", "m/s"),
    "noise_scale": ("sensor noise scale", "x the scene's SensorNoise std"),
}

#: Parameters given per body axis: a scalar value stands for the same on all three.
_PER_AXIS = ("inertia_scale", "max_torque")
#: Parameters whose every entry must be > 0, with what a value is.
_POSITIVE = {
    "inertia_scale": "a scale of the inertia",
    "max_torque": "a torque limit in N m",
    "thrust_max": "a rotor's thrust limit in N",
    "thrust_to_weight": "4 thrust_max / (m g)",
    "time_constant": "a rotor time constant in s",
}
#: Parameters whose every entry must be >= 0, with what a value is.
_NONNEGATIVE = {"noise_scale": "a factor on the scene's SensorNoise standard deviations"}


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
    if name in _PER_AXIS and v.ndim == 1:
        v = np.repeat(v[:, None], 3, axis=1)
    if v.ndim != 1 + len(shape) or v.shape[1:] != shape or v.shape[0] < 1:
        if name in _PER_AXIS:
            want = f"({leading},) or ({leading}, 3)"
        else:
            want = str((leading,) + shape)
        raise ValueError(f"params[{name!r}] must have shape {want}, got {np.shape(value)}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"params[{name!r}] must be finite")
    if name in _POSITIVE and np.any(v <= 0):
        raise ValueError(f"params[{name!r}] must be > 0 ({_POSITIVE[name]}), got min {v.min():g}")
    if name in _NONNEGATIVE and np.any(v < 0):
        raise ValueError(
            f"params[{name!r}] must be >= 0 ({_NONNEGATIVE[name]}), got min {v.min():g}"
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
        if name in _PER_AXIS and np.shape(v) == (n,):
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


def _check_noisy(scene, names) -> None:
    """``ValueError`` when ``noise_scale`` is among ``names`` and the scene has no noise."""
    if "noise_scale" in names and getattr(scene, "noise", None) is None:
        raise ValueError(
            "params['noise_scale'] scales the scene's sensor noise, and the scene has none: "
            "build it with noise=so3jax.SensorNoise(..., key=...) (nonzero standard "
            "deviations) and a control_period"
        )


def _scale_noise(scene, scale):
    """The scene with every standard deviation of its `SensorNoise` times ``scale``."""
    fields = ("attitude", "rate", "position", "velocity")
    noise = scene.noise
    c = jnp.asarray(scale, scene.y0.R.dtype)
    return eqx.tree_at(
        lambda s: tuple(getattr(s.noise, f) for f in fields),
        scene,
        tuple(c * getattr(noise, f) for f in fields),
    )


def prepare_scene(scene: Tracking, names) -> Tracking:
    """The scene with the slots the named parameters need (a disturbance, a torque limit,
    a scaled reference); ``noise_scale`` needs a scene built with noise."""
    _check_noisy(scene, names)
    dtype = scene.y0.R.dtype
    if "disturbance" in names and scene.disturbance is None:
        # A slot on the scene itself: its torque limit and control period stay.
        scene = eqx.tree_at(
            lambda s: s.disturbance, scene, jnp.zeros(3, dtype), is_leaf=lambda a: a is None
        )
    if "max_torque" in names and scene.max_torque is None:
        # No limit until a run sets one; the saved M_cmd appears as with a limit built in.
        scene = eqx.tree_at(
            lambda s: s.max_torque, scene, np.full(3, np.inf, dtype), is_leaf=lambda a: a is None
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
    if "max_torque" in values:
        scene = eqx.tree_at(lambda s: s.max_torque, scene, jnp.asarray(values["max_torque"], dtype))
    if "noise_scale" in values:
        scene = _scale_noise(scene, values["noise_scale"])
    return scene


# --------------------------------------------------------------------------
# The quadrotor's parameters
# --------------------------------------------------------------------------


def _wind_mean(wind) -> bool:
    """Whether a wind model ``t -> w(t)`` carries its mean as a ``mean`` array of shape (3,)."""
    mean = getattr(wind, "mean", None)
    return eqx.is_array(mean) and np.shape(mean) == (3,)


def prepare_quadrotor(scene, values: Mapping[str, np.ndarray]):
    """The quadrotor checked against the parameters' values, with the slots they need.

    ``thrust_max``/``thrust_to_weight`` and ``time_constant`` vary the scene's
    `Rotors` (``time_constant``: rotors built with one, so that their thrusts are
    state); ``wind_speed`` needs ``drag`` and sets a constant wind (a slot of zeros
    when the scene has none), or the ``mean`` of a wind model that has one;
    ``noise_scale`` needs a scene built with ``noise``. A ``ValueError`` names the
    parameter and says how to build the scene otherwise.

    **Arguments:**

    - `scene`: a `Quadrotor`.
    - `values`: name -> the checked values, `(n, ...)` (`check_params`, `draw`).

    **Returns:** the scene, with a wind slot where ``wind_speed`` needs one.
    """
    names = set(values)
    _check_noisy(scene, names)
    thrust = [n for n in ("thrust_max", "thrust_to_weight") if n in names]
    if len(thrust) > 1:
        raise ValueError(
            "params: give thrust_max or thrust_to_weight (= 4 thrust_max / (m g)), not both"
        )
    rotors = scene.rotors
    for name in thrust + [n for n in ("time_constant",) if n in names]:
        if rotors is None:
            raise ValueError(
                f"params[{name!r}] varies the rotors: build the scene with "
                "scenes.quadrotor(..., rotors=so3jax.Rotors(arm, torque_coefficient, ...))"
            )
    if "time_constant" in names and not rotors.lagged:
        raise ValueError(
            "params['time_constant'] varies the rotor lag, and the scene has none: it must be "
            "built with one, scenes.quadrotor(..., rotors=so3jax.Rotors(..., time_constant=tau)), "
            "so that the rotor thrusts are state"
        )
    if thrust:
        name = thrust[0]
        mg = float(np.asarray(scene.vehicle.mass, np.float64) * np.asarray(scene.vehicle.g))
        v = np.asarray(values[name], np.float64)
        f_max = v * (mg / 4.0) if name == "thrust_to_weight" else v
        hover = v < 1.0 if name == "thrust_to_weight" else 4.0 * v < mg
        if np.any(hover):
            raise ValueError(
                f"params[{name!r}] must let the rotors hover the vehicle (4 thrust_max >= m g "
                f"= {mg:g} N, thrust_to_weight >= 1), got min {v.min():g}"
            )
        lo = float(np.asarray(rotors.thrust_min, np.float64))
        if np.any(f_max <= lo):
            raise ValueError(
                f"params[{name!r}] must give a thrust_max above the rotors' thrust_min "
                f"({lo:g} N), got a thrust_max of {f_max.min():g} N"
            )
    if "wind_speed" in names:
        if scene.drag is None:
            raise ValueError(
                "params['wind_speed'] acts through the drag: build the scene with "
                "scenes.quadrotor(..., drag=d)"
            )
        if scene.wind is None:
            dtype = scene.y0.R.dtype
            scene = eqx.tree_at(
                lambda s: s.wind, scene, np.zeros(3, dtype), is_leaf=lambda a: a is None
            )
        elif callable(scene.wind) and not _wind_mean(scene.wind):
            raise ValueError(
                "params['wind_speed'] sets a constant mean wind, and the scene's wind is a "
                "function t -> w(t) without a `mean` array: build the scene with a constant "
                "wind (or none) to sweep it"
            )
    return scene


def apply_quadrotor_params(scene, values: Mapping[str, Array]):
    """The quadrotor with one value of each parameter (traceable: works under `vmap`).

    ``thrust_to_weight`` ``r`` sets ``thrust_max = r m g / 4``. ``Omega0`` is applied
    by the caller (it is part of the initial state); the lagged rotor thrusts and a
    held control start anew from the run's initial state (`Quadrotor.for_step`).
    """
    dtype = scene.y0.R.dtype
    f_max = None
    if "thrust_max" in values:
        f_max = jnp.asarray(values["thrust_max"], dtype)
    elif "thrust_to_weight" in values:
        v = scene.vehicle
        f_max = jnp.asarray(values["thrust_to_weight"], dtype) * (v.mass * v.g / 4.0)
    if f_max is not None:
        scene = eqx.tree_at(lambda s: s.rotors.thrust_max, scene, f_max)
    if "time_constant" in values:
        tau = jnp.asarray(values["time_constant"], dtype)
        scene = eqx.tree_at(lambda s: s.rotors.time_constant, scene, tau)
    if "wind_speed" in values:
        w = jnp.asarray(values["wind_speed"], dtype)
        if callable(scene.wind):
            scene = eqx.tree_at(lambda s: s.wind.mean, scene, w)
        else:
            scene = eqx.tree_at(lambda s: s.wind, scene, w)
    if "noise_scale" in values:
        scene = _scale_noise(scene, values["noise_scale"])
    return scene
