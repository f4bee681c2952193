"""How `so3jax.sweep` treats each kind of scene: one small strategy object per scene class.

`sweep` knows the gains, the initial attitudes, the chunks, the refinement of failed
runs and the chunk files; what one run *is* comes from the scene's hook,
``scene.sweep_hook()`` (`sweep_hook` falls back to `AttitudeSweep` for a scene
without one):

- `params`: the scene parameters it can vary (names of `so3jax._sweep_params.PARAMS`);
  `accept` rejects the others with a ``ValueError`` naming them;
- `check`: whether the scene can be swept at all;
- `prepare`: the values checked against the scene and the slots they need added, once;
  `apply`: one run's values put into the scene (traceable, under `vmap`);
- `with_noise_key`: one run's key put into the scene's `SensorNoise` (a scene with
  ``noise``; `so3jax._sweep.noise_key`);
- `initial_rate`: the scene's own ``Omega0``, around which the runs' rates are drawn;
- `stable_dt`: the step limit per gain pair and column, which tells a numerical failure
  from a diverged closed loop;
- `thresholds`: what a run's settling is judged by;
- `run`: one run from ``(R0, Omega0)`` with gains ``(k_R, k_Omega)`` and its statistics
  (`so3jax._sweep.STAT_FIELDS`, ``status_code``, ``fail_step``, and any further
  metrics, which `SweepResult.metrics` collects).

`AttitudeSweep` is the hook of `Tracking` and `SampledTracking`; `QuadrotorSweep` that
of `Quadrotor`. A new parameter takes a few lines: its name and the shape of one value
at the end of `PARAMS` (with its label in `PARAM_LABELS`), its name in the hook's
`params`, and a branch in the function `apply` calls that puts the value into the scene
(and, if the scene needs a slot for it, one in `prepare`).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._so3 import _attitude_error_function
from ._stability import stability_interval, stability_polynomial, stable_dt
from ._sweep_params import (
    apply_params,
    apply_quadrotor_params,
    prepare_quadrotor,
    prepare_scene,
)
from ._trajectory import OK, settling_time


def sweep_hook(scene) -> SweepHook:
    """The scene's `SweepHook` (``scene.sweep_hook()``), `AttitudeSweep` by default."""
    hook = getattr(scene, "sweep_hook", None)
    return AttitudeSweep() if hook is None else hook()


def _stats(traj, psi, t_settle, cost) -> dict:
    """The statistics every run returns (`so3jax._sweep.STAT_FIELDS` and its status)."""
    ok = traj.status.code == OK
    nan = jnp.array(jnp.nan, psi.dtype)
    return {
        "final_psi": psi[-1],
        "settling_time": jnp.where(ok, t_settle, nan),
        "peak_torque": jnp.where(ok, jnp.max(jnp.sqrt(jnp.sum(traj.M**2, -1))), nan),
        "cost": cost,
        "status_code": traj.status.code,
        "fail_step": traj.status.step,
    }


class SweepHook:
    """How `sweep` treats one kind of scene (see the module's docstring).

    The base class holds what every kind shares; `AttitudeSweep` and
    `QuadrotorSweep` fill in the rest.
    """

    #: The scene, in words, for error messages.
    kind: ClassVar[str] = "this scene"
    #: The `sweep` parameters this kind of scene takes.
    params: ClassVar[tuple[str, ...]] = ("Omega0",)
    #: Appended to the error on a parameter it does not take.
    hint: ClassVar[str] = ""

    def check(self, scene) -> None:
        """``ValueError`` (or ``TypeError``) unless `sweep` can run ``scene``."""

    def accept(self, names) -> None:
        """``ValueError`` naming the parameters among ``names`` this scene does not take."""
        bad = sorted(set(names) - set(self.params))
        if bad:
            takes = ", ".join(repr(p) for p in self.params)
            raise ValueError(f"params {bad} cannot vary {self.kind}; it takes {takes}{self.hint}")

    def prepare(self, scene, values: Mapping[str, np.ndarray]):
        """The scene checked against the parameters' values, with the slots they need."""
        return scene

    def apply(self, scene, values: Mapping):
        """The scene with one run's parameter values (``Omega0`` apart; traceable)."""
        return scene

    def with_noise_key(self, scene, key):
        """The scene whose `SensorNoise` draws from ``key`` (one run's key, traceable)."""
        return eqx.tree_at(lambda s: s.noise.key, scene, key)

    def initial_rate(self, scene):
        """The scene's initial body rate ``Omega0``, shape `(3,)`."""
        return scene.y0.x[:3]

    def thresholds(self, threshold: float, position_threshold: float):
        """``(what run judges settling by, the position threshold a result records)``."""
        return threshold, None

    def stable_dt(
        self, scene, method, k_R, k_Omega, safety: float, columns: Mapping, n: int
    ) -> np.ndarray:
        """The largest step known to be stable for each gain pair and column, `(G, n)`.

        ``columns``: the swept parameters' values per column, name -> `(n, ...)`.
        ``inf`` where no mode limits the step, NaN where the limit is not known.
        """
        raise NotImplementedError

    def run(
        self, scene, method, dt, n_steps, save_every, threshold, weights, k_R, k_O, R0, W0, pv,
        scalarize,
    ) -> dict:  # fmt: skip
        """One run's statistics: gains ``(k_R, k_O)``, start ``(R0, W0)``, values ``pv``."""
        raise NotImplementedError


class AttitudeSweep(SweepHook):
    """A tracking scene with the geometric controller (`scenes.tracking`, `scenes.seed`).

    Its reference, inertia and ``Rd0`` are kept; each run sets the gains and starts
    from ``(R0, Omega0)`` apart from the scene's attitudes (the runs share ``Rd``). A
    run settles when ``Psi(R, Rd) < threshold`` for good; its cost is `tracking_cost`.
    The step limit is `stable_dt` of the (scaled) inertia.
    """

    kind: ClassVar[str] = "an attitude tracking scene"
    params: ClassVar[tuple[str, ...]] = (
        "inertia_scale",
        "disturbance",
        "Omega0",
        "reference_amplitude",
        "max_torque",
        "noise_scale",
    )
    hint: ClassVar[str] = (
        " (thrust_max, thrust_to_weight, time_constant and wind_speed vary a quadrotor)"
    )

    def check(self, scene) -> None:
        from ._tune import _check_tracking_scene

        _check_tracking_scene(scene)

    def prepare(self, scene, values):
        return prepare_scene(scene, values)

    def apply(self, scene, values):
        return apply_params(scene, values) if values else scene

    def stable_dt(self, scene, method, k_R, k_Omega, safety, columns, n):
        J = np.asarray(scene.body.inertia, np.float64)
        if "inertia_scale" not in columns:
            return np.repeat(stable_dt(method, J, k_R, k_Omega, safety)[:, None], n, axis=1)
        scales, which = np.unique(columns["inertia_scale"], axis=0, return_inverse=True)
        inertias = [np.sqrt(sc)[:, None] * J * np.sqrt(sc) for sc in scales]
        st = np.stack([stable_dt(method, Ji, k_R, k_Omega, safety) for Ji in inertias], 1)
        for sc, Ji in zip(scales, inertias, strict=True):
            m = np.sort(np.linalg.eigvalsh(Ji))
            if m[0] + m[1] < m[2] * (1 - 1e-12):
                warnings.warn(
                    f"params['inertia_scale'] {sc} gives principal moments {m} that violate "
                    "the triangle inequality J1 + J2 >= J3: no physical rigid body has them",
                    stacklevel=3,  # the caller of `sweep`
                )
                break
        return st[:, which.reshape(-1)]

    def run(
        self, scene, method, dt, n_steps, save_every, threshold, weights, k_R, k_O, R0, W0, pv,
        scalarize,
    ):  # fmt: skip
        from ._simulate import simulate_from
        from ._tune import _tracking_cost, with_gains, with_start

        sc = self.apply(scene, pv)
        # The start goes in apart from the scene's attitudes, so the runs share Rd.
        sc, R0 = with_start(with_gains(sc, k_R, k_O), R0, W0)
        traj = simulate_from(sc, R0, method, dt, n_steps, save_every, scalarize)
        psi = _attitude_error_function(traj.R, traj.Rd)
        t_settle = settling_time(traj.t, psi < threshold)
        # (summed the same in every chunk: a chunked sweep equals a whole one bit for bit)
        cost = _tracking_cost(traj, sc.reference, weights, chunk_invariant=True)  # (checked)
        return _stats(traj, psi, t_settle, cost)


class QuadrotorSweep(SweepHook):
    """A quadrotor (`scenes.quadrotor`, e.g. `scenes.quadrotor_recovery()`).

    Its attitude gains ``k_R``, ``k_Omega`` are swept; ``k_x``, ``k_v``, the vehicle,
    the reference, ``x0``, ``v0`` and the control period are kept. Statistics are taken
    against the commanded attitude ``Rc``; a run settles when ``Psi(R, Rc) <
    threshold`` *and* ``|e_x| < position_threshold``; its cost integrates
    ``|e_x|^2 + w_Psi Psi(R, Rc) + w_Omega |e_Omega|^2 + w_M |M|^2`` by the trapezoidal
    rule; `position_metrics` adds the position errors and the least thrust-axis
    cosine. Held feedback (``control_period``) sets no step limit, continuous feedback
    that of `stable_dt`; a rotor lag ``tau`` adds ``safety * interval * tau``, the
    limit of the method (`stability_interval`) on the lag's mode ``-1/tau``.
    """

    kind: ClassVar[str] = "a quadrotor scene"
    params: ClassVar[tuple[str, ...]] = (
        "Omega0",
        "thrust_max",
        "thrust_to_weight",
        "time_constant",
        "wind_speed",
        "noise_scale",
    )
    hint: ClassVar[str] = " (vary the rest of the vehicle by building scenes with scenes.quadrotor)"

    def prepare(self, scene, values):
        return prepare_quadrotor(scene, values)

    def apply(self, scene, values):
        return apply_quadrotor_params(scene, values) if values else scene

    def thresholds(self, threshold, position_threshold):
        return (threshold, position_threshold), position_threshold

    def stable_dt(self, scene, method, k_R, k_Omega, safety, columns, n):
        G = np.shape(k_R)[0]
        if scene.sampled:
            st = np.full((G, n), np.inf)
        else:
            J = np.asarray(scene.vehicle.body.inertia, np.float64)
            st = np.repeat(stable_dt(method, J, k_R, k_Omega, safety)[:, None], n, axis=1)
        if scene.lagged and stability_polynomial(method) is not None:
            tau = columns.get("time_constant")
            if tau is None:
                tau = np.full(n, float(np.asarray(scene.rotors.time_constant, np.float64)))
            st = np.minimum(st, safety * stability_interval(method) * np.asarray(tau)[None, :])
        return st

    def run(
        self, scene, method, dt, n_steps, save_every, threshold, weights, k_R, k_O, R0, W0, pv,
        scalarize,
    ):  # fmt: skip
        from ._quadrotor import _restart, position_metrics
        from ._simulate import simulate

        psi_thr, pos_thr = threshold
        dtype = scene.y0.R.dtype
        sc = self.apply(scene, pv)
        sc = eqx.tree_at(
            lambda s: (s.gains.k_R, s.gains.k_Omega),
            sc,
            (jnp.asarray(k_R, dtype), jnp.asarray(k_O, dtype)),
        )
        y0 = _restart(sc, R0)
        y0 = type(y0)(y0.R, y0.x.at[0:3].set(jnp.asarray(W0, dtype)))
        sc = eqx.tree_at(lambda s: s.y0, sc, y0)
        traj = simulate(sc, method, dt, n_steps, save_every, scalarize=scalarize)
        ex = traj.extras
        psi = ex["Psi"]
        e, extra = position_metrics(traj)
        t_settle = settling_time(traj.t, (psi < psi_thr) & (e < pos_thr))
        f = (
            e**2
            + weights.psi * psi
            + weights.omega * jnp.sum(ex["e_Omega"] ** 2, -1)
            + weights.effort * jnp.sum(traj.M**2, -1)
        )
        cost = jnp.sum(0.5 * (f[1:] + f[:-1]) * jnp.diff(traj.t))
        out = _stats(traj, psi, t_settle, cost)
        nan = jnp.array(jnp.nan, dtype)
        ok = traj.status.code == OK
        out.update({k: jnp.where(ok, v, nan) for k, v in extra.items()})
        return out
