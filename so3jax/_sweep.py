"""Batched Monte Carlo sweeps: gains crossed with random initial attitudes.

A sweep is `jax.vmap` of `simulate` over a flat list of runs (gain pair ``g``,
attitude ``i``), cut into chunks of bounded memory. Each chunk is sharded over
the devices along its batch axis (`jax.sharding.NamedSharding` over a 1-D
`jax.sharding.Mesh`), so the same call runs on one CPU, several GPUs or several
hosts. Per run only a few numbers come back (final ``Psi``, settling time, peak
torque, integrated cost, status); with a `results_dir` every finished chunk is
written to its own ``.npz`` file at once, so an interrupted sweep resumes where
it stopped.

Several processes (several machines) run one sweep on JAX's multi-controller
runtime: every process calls `jax.distributed.initialize` and then `sweep` with
the same arguments. The mesh then spans every process's devices and each
process computes its shard of every chunk (and of the re-runs that resolve its
failures); the shards are gathered after each chunk
(`multihost_utils.process_allgather`), so every process holds the whole chunk,
takes the same refinement decisions and returns the same `SweepResult`. One
sharded program per chunk was chosen over handing whole chunks to processes in
turn: it needs no merge step and no bookkeeping of who owns which chunk, every
collective is one JAX already provides, and the processes stay in step (each
chunk's re-runs are sharded too). Only process 0 touches `results_dir`: it writes the chunk
files, and on a resume it decides which chunks exist and sends their contents
to the others (`multihost_utils.broadcast_one_to_all`), so the folder need not
be on a shared file system.

Attitude ``i`` is drawn from ``jax.random.fold_in(key, i)``: it does not depend
on the number of attitudes, and every gain pair sees the same attitudes (common
random numbers, so differences between gains are not sampling noise). A scene with
sensor noise (`SensorNoise`) draws it, in every run from attitude ``i``, from
``noise_key(key, i) = fold_in(fold_in(key, i), 2**31 - 1)`` in place of its own key:
common random numbers again, across gain pairs and parameter combinations.

A run that stops being finite is re-run, right after its chunk, at a smaller
step known to be stable for its gains (`so3jax.stable_dt`; halvings of ``dt``
with the saved points at the same times). It then ends in one of three
classes: *numerical* (finite at the smaller step: the statistics come from that
run), *diverged* (it fails at a step known to be stable: the closed loop
itself diverges) or *unresolved* (the stable step needs more halvings than
`refine` allows).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import io
import json
import math
import os
import time
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._engine import plan as _plan
from ._engine.policy import current
from ._integrators import RKMK4, AbstractLieSolver
from ._so3 import random_rotation
from ._stability import SAFETY
from ._sweep_hooks import sweep_hook
from ._sweep_params import check_params, draw, split_params
from ._trajectory import OK, _check_int
from ._tune import CostWeights, _check_weights
from ._types import Array

#: Per-run statistics, taken from the run that resolved a failure.
STAT_FIELDS = ("final_psi", "settling_time", "peak_torque", "cost")
#: Per-run fields of a `SweepResult`, as stored in the chunk files.
RUN_FIELDS = STAT_FIELDS + ("status_code", "fail_step", "outcome", "run_dt")

#: Outcome codes of a run (`SweepResult.outcome`): finite at the requested step;
#: failed there and resolved at a smaller stable step; failed at a step known to be
#: stable (the closed loop diverged); failed, and no stable step within the budget.
FINITE, NUMERICAL, DIVERGED, UNRESOLVED = 0, 1, 2, 3
OUTCOMES = {
    FINITE: "finite at dt",
    NUMERICAL: "numerical (resolved at a smaller step)",
    DIVERGED: "diverged (closed loop)",
    UNRESOLVED: "unresolved (no stable step within the refinement budget)",
}


@dataclasses.dataclass(frozen=True)
class SweepResult:
    """Per-run results and per-gain statistics of a `sweep`.

    Runs are indexed ``[g, i]``: gain pair ``g``, initial attitude ``i``. Each
    run ends in one of four outcomes: *settled* (``Psi < threshold`` for good
    within the horizon), *not settled*, *diverged* (the closed loop fails at a
    step known to be stable) or *numerical* (it failed only because ``dt``
    exceeded the method's stability limit, and was resolved at a smaller step;
    it then also settled or not). A failed run whose stable step needs more
    halvings than the refinement budget is *unresolved*. Statistics leave out
    diverged and unresolved runs; a gain pair whose runs all failed has NaN
    statistics and a failure fraction of 1.

    **Fields:**

    - `k_R`, `k_Omega`: the gain pairs, shape `(G,)` (or `(G, 3)` per axis).
    - `grid_shape`: ``(len(k_R), len(k_Omega))`` for a grid sweep (pair
      ``g = a * len(k_Omega) + b``), ``None`` for a list of pairs.
    - `R0`: initial attitudes, shape `(N, 3, 3)`; `Omega0`: rates, `(N, 3)`.
    - `final_psi`: ``Psi(R, Rd)`` at the end, shape `(G, N)`.
    - `settling_time`: first saved time after which ``Psi < threshold`` for
      good, shape `(G, N)`; ``inf`` if it never settles, NaN if it failed.
    - `peak_torque`: ``max |M|`` over the saved points, shape `(G, N)`.
    - `cost`: `tracking_cost` of the run, shape `(G, N)`.
    - `status_code`, `fail_step`: the `Status` of the run at the requested
      ``dt``, shape `(G, N)`.
    - `outcome`: 0 finite at ``dt``, 1 numerical, 2 diverged, 3 unresolved,
      shape `(G, N)` (see `numerical`, `diverged`, `unresolved`).
    - `run_dt`: the step of the run the statistics come from (``dt``, or the
      smaller step that resolved or confirmed a failure; NaN if unresolved),
      shape `(G, N)`.
    - `stable_dt`: the largest step known to be stable for each gain pair
      (`so3jax.stable_dt`), shape `(G,)`.
    - `threshold`, `dt`, `n_steps`, `save_every`, `refine`: the settings.
    - `params`: the swept scene parameters by name, one value per column
      ``i``, shape `(N, ...)` (empty without ``params``); column
      ``i = p * n_attitudes + a`` is combination ``p`` from attitude ``a``.
    - `metrics`: further per-run statistics by name, shape `(G, N)` (a
      quadrotor sweep: ``final_position_error``, ``max_position_error``,
      ``rms_position_error``, ``min_thrust_axis_up``; NaN where a run failed).
    - `position_threshold`: a quadrotor sweep's settling threshold on ``|e_x|``
      (m); ``None`` for an attitude scene.
    - `scalarize`: the program each chunk was asked to run, scalarized (``True``) or
      the array program: the caller's ``scalarize``, or the platform's choice.

    For a quadrotor, ``Psi``, ``e_Omega`` and the settling test are taken against
    the commanded attitude ``Rc``, and settling also needs ``|e_x| <
    position_threshold``.
    """

    k_R: np.ndarray
    k_Omega: np.ndarray
    grid_shape: tuple[int, int] | None
    R0: np.ndarray
    Omega0: np.ndarray
    final_psi: np.ndarray
    settling_time: np.ndarray
    peak_torque: np.ndarray
    cost: np.ndarray
    status_code: np.ndarray
    fail_step: np.ndarray
    outcome: np.ndarray
    run_dt: np.ndarray
    stable_dt: np.ndarray
    threshold: float
    dt: float
    n_steps: int
    save_every: int
    refine: int
    params: dict = dataclasses.field(default_factory=dict)
    metrics: dict = dataclasses.field(default_factory=dict)
    position_threshold: float | None = None
    scalarize: bool = False

    @property
    def diverged(self) -> np.ndarray:
        """Runs whose closed loop diverged (they failed at a step known to be stable), `(G, N)`."""
        return self.outcome == DIVERGED

    @property
    def numerical(self) -> np.ndarray:
        """Runs that failed only numerically (step past the stability limit), `(G, N)`.

        They were resolved at the smaller step `run_dt`; their statistics come from there.
        """
        return self.outcome == NUMERICAL

    @property
    def unresolved(self) -> np.ndarray:
        """Runs that failed at ``dt`` with no stable step within `refine` halvings, `(G, N)`."""
        return self.outcome == UNRESOLVED

    @property
    def failed(self) -> np.ndarray:
        """Runs with no statistics: diverged or unresolved, shape `(G, N)`."""
        return self.diverged | self.unresolved

    @property
    def settled(self) -> np.ndarray:
        """Runs (numerical ones included) that settled within the horizon, shape `(G, N)`."""
        return ~self.failed & np.isfinite(self.settling_time)

    @property
    def not_settled(self) -> np.ndarray:
        """Runs that stayed finite (at ``dt`` or after refinement) but did not settle, `(G, N)`."""
        return ~self.failed & ~np.isfinite(self.settling_time)

    @property
    def dt_stable_all(self) -> float:
        """A step stable for every gain pair of the sweep (the smallest `stable_dt`)."""
        return float(np.min(self.stable_dt))

    def _masked(self, values: np.ndarray) -> np.ndarray:
        return np.where(self.failed, np.nan, values)

    @property
    def median_settling_time(self) -> np.ndarray:
        """Median settling time per gain pair over runs with statistics, shape `(G,)`.

        Runs that never settle count as ``inf`` (a censored sample: the median
        is exact while fewer than half are censored, ``inf`` otherwise).
        """
        return _nan_reduce(np.nanmedian, self._masked(self.settling_time))

    def settling_quantile(self, q: float) -> np.ndarray:
        """Quantile ``q`` of the settling time per gain pair (runs with statistics), `(G,)`."""
        return _nan_reduce(
            lambda a, axis: np.nanquantile(a, q, axis=axis), self._masked(self.settling_time)
        )

    @property
    def not_settled_fraction(self) -> np.ndarray:
        """Fraction of runs per gain pair that did not settle, for any reason, shape `(G,)`.

        ``1 - settled.mean(axis=1)``: a run counts whether it stayed finite and did
        not settle within the horizon, diverged, or stayed unresolved (`not_settled`
        marks only the first kind).
        """
        return 1.0 - self.settled.mean(axis=1)

    @property
    def failure_fraction(self) -> np.ndarray:
        """Alias of `not_settled_fraction`, shape `(G,)`.

        Despite the name it counts every run that did not settle, not only the
        failed ones (`diverged_fraction` counts those whose closed loop diverged).
        """
        return self.not_settled_fraction

    @property
    def diverged_fraction(self) -> np.ndarray:
        """Fraction of runs per gain pair whose closed loop diverged, shape `(G,)`."""
        return self.diverged.mean(axis=1)

    @property
    def numerical_fraction(self) -> np.ndarray:
        """Fraction of runs per gain pair that failed only numerically, shape `(G,)`."""
        return self.numerical.mean(axis=1)

    @property
    def mean_cost(self) -> np.ndarray:
        """Mean tracking cost per gain pair over runs with statistics, shape `(G,)`."""
        return _nan_reduce(np.nanmean, self._masked(self.cost))

    @property
    def mean_final_psi(self) -> np.ndarray:
        """Mean final ``Psi`` per gain pair over runs with statistics, shape `(G,)`."""
        return _nan_reduce(np.nanmean, self._masked(self.final_psi))

    @property
    def max_peak_torque(self) -> np.ndarray:
        """Largest peak torque per gain pair over runs with statistics, shape `(G,)`."""
        return _nan_reduce(np.nanmax, self._masked(self.peak_torque))

    def as_grid(self, values: np.ndarray) -> np.ndarray:
        """Per-gain values `(G, ...)` reshaped to ``(len(k_R), len(k_Omega), ...)``."""
        if self.grid_shape is None:
            raise ValueError("as_grid needs a grid sweep (grid=True)")
        values = np.asarray(values)
        return values.reshape(self.grid_shape + values.shape[1:])

    def best(self, statistic: str = "mean_cost") -> int:
        """Index of the gain pair with the smallest `statistic` (NaN never wins)."""
        values = np.asarray(getattr(self, statistic), dtype=float)
        if values.shape != (self.k_R.shape[0],):
            raise ValueError(f"statistic must be a per-gain statistic, got {statistic!r}")
        values = np.where(np.isnan(values), np.inf, values)
        return int(np.argmin(values))

    def worst_attitudes(self, g: int, n: int = 5) -> np.ndarray:
        """Indices of the ``n`` slowest initial attitudes for gain pair ``g`` (failed first)."""
        t = np.where(self.failed[g], np.inf, self.settling_time[g])
        return np.argsort(-np.nan_to_num(t, posinf=np.finfo(float).max), kind="stable")[:n]

    def outcome_counts(self) -> dict:
        """Runs per outcome: settled, not settled, numerical, diverged, unresolved.

        Numerical runs are also counted as settled or not settled (from their
        resolved run), so the first two and the last two add up to all runs.
        """
        return {
            "settled": int(self.settled.sum()),
            "not_settled": int(self.not_settled.sum()),
            "numerical": int(self.numerical.sum()),
            "diverged": int(self.diverged.sum()),
            "unresolved": int(self.unresolved.sum()),
        }

    def param_summary(self, bins: int = 4) -> dict:
        """Outcomes by value of each swept parameter (over all gain pairs and attitudes).

        A parameter with few distinct values (a grid, a short list) is listed value
        by value. One with many (draws from a distribution, one per attitude) is
        *continuous*: its columns are split into `bins` quantile bins, each
        labelled by the range of values it holds; a 3-vector is binned by its
        entry when its three entries are equal in every column, by its norm
        otherwise. The rule (`is_continuous`): with ``n`` distinct values over
        ``N`` columns (combinations x attitudes), a parameter is continuous when
        ``n > bins`` and ``n^2 > N``, i.e. when its values average fewer columns
        each than there are values.

        **Arguments:**

        - `bins`: number of quantile bins of a continuous parameter, >= 1.

        **Returns:** ``{name: [row, ...]}``; each row holds ``"label"`` (the
        value, or the range of a bin, as text), ``"binned"``, ``"value"`` (a
        listed value) or ``"range"`` (``[low, high]`` of a bin; of the norm when
        ``"of"`` is ``"norm"``), and the outcomes ``"runs"``,
        ``"settled_fraction"``, ``"numerical"``, ``"diverged"``, ``"unresolved"``,
        ``"mean_cost"`` (``None`` if no run has statistics).
        """
        if isinstance(bins, bool) or not isinstance(bins, int | np.integer) or bins < 1:
            raise ValueError(f"bins must be an integer >= 1, got {bins!r}")
        out = {}
        for name, col in self.params.items():
            col = np.asarray(col).reshape(col.shape[0], -1)
            values, inverse = np.unique(col, axis=0, return_inverse=True)
            inverse = inverse.reshape(-1)
            rows = []
            if not is_continuous(values.shape[0], col.shape[0], bins):
                for k, v in enumerate(values):
                    value = v.tolist() if v.size > 1 else float(v[0])
                    row = {"label": str(value), "binned": False, "value": value}
                    rows.append(row | self._outcomes(inverse == k))
            else:
                isotropic = bool(np.all(col == col[:, :1]))
                of = "value" if isotropic else "norm"
                q = col[:, 0] if isotropic else np.linalg.norm(col, axis=1)
                edges = np.quantile(q, np.linspace(0.0, 1.0, bins + 1))
                which = np.searchsorted(edges[1:-1], q, side="right")
                for k in range(bins):
                    cols = which == k
                    if not cols.any():  # ties merged it into a neighbour
                        continue
                    lo, hi = float(q[cols].min()), float(q[cols].max())
                    text = f"[{lo:.4g}, {hi:.4g}]"
                    row = {
                        "label": text if of == "value" else f"|v| in {text}",
                        "binned": True,
                        "of": of,
                        "range": [lo, hi],
                    }
                    rows.append(row | self._outcomes(cols))
            out[name] = rows
        return out

    def _outcomes(self, cols: np.ndarray) -> dict:
        """The outcomes of the runs in columns ``cols`` (a boolean mask), over all gains."""
        cost = self._masked(self.cost)[:, cols]
        return {
            "runs": int(cols.sum() * self.cost.shape[0]),
            "settled_fraction": float(self.settled[:, cols].mean()),
            "numerical": int(self.numerical[:, cols].sum()),
            "diverged": int(self.diverged[:, cols].sum()),
            "unresolved": int(self.unresolved[:, cols].sum()),
            "mean_cost": float(np.nanmean(cost)) if np.isfinite(cost).any() else None,
        }

    def summary(self) -> dict:
        """A JSON-ready summary: outcome counts, the stable step, and the best gain pair."""
        b = self.best()
        counts = self.outcome_counts()
        resolved = np.unique(self.run_dt[self.numerical])
        beyond = self.dt > self.stable_dt
        return {
            "n_gains": int(self.k_R.shape[0]),
            "n_attitudes": int(self.R0.shape[0]),
            "n_runs": int(self.cost.size),
            "threshold": self.threshold,
            "position_threshold": self.position_threshold,
            "horizon": self.dt * self.n_steps,
            "dt": self.dt,
            "outcomes": counts,
            "diverged_runs": counts["diverged"],
            "numerical_runs": counts["numerical"],
            "unresolved_runs": counts["unresolved"],
            "numerical_resolved_at_dt": [float(v) for v in resolved],
            "stable_dt_all_gains": self.dt_stable_all,
            "gains_beyond_stable_dt": int(beyond.sum()),
            "not_settled_fraction_overall": float(1.0 - self.settled.mean()),
            "failure_fraction_overall": float(1.0 - self.settled.mean()),  # the same (alias)
            "params": self.param_summary(),
            "best": {
                "k_R": np.asarray(self.k_R[b]).tolist(),
                "k_Omega": np.asarray(self.k_Omega[b]).tolist(),
                "mean_cost": float(self.mean_cost[b]),
                "median_settling_time": float(self.median_settling_time[b]),
                "not_settled_fraction": float(self.not_settled_fraction[b]),
                "failure_fraction": float(self.not_settled_fraction[b]),  # the same (alias)
            },
        }

    def summary_table(self) -> str:
        """The outcome counts, the stable step and the outcomes by parameter as a text table.

        Parameters are listed as `param_summary` gives them: value by value, or in
        quantile bins for a continuous one.
        """
        n = self.cost.size
        c = self.outcome_counts()
        resolved = ", ".join(f"{v:.3g}" for v in np.unique(self.run_dt[self.numerical]))
        rows = [
            (
                "settled",
                c["settled"],
                f"Psi < {self.threshold:g}{self._position_note()} within "
                f"{self.dt * self.n_steps:g} s",
            ),
            ("not settled", c["not_settled"], "finite, did not settle within the horizon"),
            (
                "numerical",
                c["numerical"],
                f"failed at dt = {self.dt:g}, resolved at dt = {resolved}" if resolved else "-",
            ),
            ("diverged", c["diverged"], "the closed loop failed at a stable step"),
            ("unresolved", c["unresolved"], f"no stable step within {self.refine} halvings"),
        ]
        lines = [f"{'outcome':<12} {'runs':>8} {'share':>7}  note"]
        lines += [f"{k:<12} {v:>8d} {v / n:>7.1%}  {note}" for k, v, note in rows]
        beyond = int(np.sum(self.dt > self.stable_dt))
        if np.all(np.isinf(self.stable_dt)):
            lines.append(
                "no gain pair limits the step (the feedback is held over each step): a "
                "failure confirmed at half the step is the closed loop diverging"
            )
        else:
            lines.append(
                f"dt = {self.dt:g} is beyond the stability limit for {beyond} of "
                f"{self.stable_dt.size} gain pairs; dt <= {self.dt_stable_all:.3g} is stable "
                "for all"
            )
        for name, rows in self.param_summary().items():
            if rows and rows[0]["binned"]:
                col = np.asarray(self.params[name])
                n_values = np.unique(col.reshape(col.shape[0], -1), axis=0).shape[0]
                what = name if rows[0]["of"] == "value" else f"|{name}|"
                lines.append(f"by {name} ({n_values} distinct values; quantile bins of {what}):")
            else:
                lines.append(f"by {name}:")
            for r in rows:
                cost = "nan" if r["mean_cost"] is None else f"{r['mean_cost']:.4g}"
                lines.append(
                    f"  {r['label']:<24} settled {r['settled_fraction']:>6.1%}  "
                    f"numerical {r['numerical']}  diverged {r['diverged']}  mean cost {cost}"
                )
        return "\n".join(lines)

    def _position_note(self) -> str:
        if self.position_threshold is None:
            return ""
        return f" (against Rc) and |e_x| < {self.position_threshold:g} m"

    def save(self, path: str | os.PathLike) -> None:
        """Write everything to one ``.npz`` file (see `load`)."""
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        for name, value in fields.pop("params").items():
            fields[f"param__{name}"] = value
        for name, value in fields.pop("metrics").items():
            fields[f"metric__{name}"] = value
        pt = fields.pop("position_threshold")
        fields["position_threshold"] = np.nan if pt is None else pt
        gs = fields.pop("grid_shape")
        fields["grid_shape"] = np.asarray(gs if gs is not None else (-1, -1))
        np.savez(path, **{k: np.asarray(v) for k, v in fields.items()})

    @classmethod
    def load(cls, path: str | os.PathLike) -> SweepResult:
        """Read a file written by `save`."""
        with np.load(path) as z:
            d = {k: z[k] for k in z.files}
        params = {k[len("param__") :]: d.pop(k) for k in list(d) if k.startswith("param__")}
        metrics = {k[len("metric__") :]: d.pop(k) for k in list(d) if k.startswith("metric__")}
        pt = float(d.pop("position_threshold", np.nan))
        required = [
            f
            for f in dataclasses.fields(cls)
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        ]
        missing = [f.name for f in required if f.name not in d]
        if missing:
            raise ValueError(
                f"{path} was written by an older so3jax (no {', '.join(missing)}): it cannot "
                "tell numerical failures from divergence; run the sweep again"
            )
        gs = tuple(int(v) for v in d.pop("grid_shape"))
        for name in ("threshold", "dt"):
            d[name] = float(d[name])
        for name in ("n_steps", "save_every", "refine"):
            d[name] = int(d[name])
        d["scalarize"] = bool(d.get("scalarize", False))
        return cls(
            grid_shape=None if gs == (-1, -1) else gs,
            params=params,
            metrics=metrics,
            position_threshold=None if np.isnan(pt) else pt,
            **d,
        )


def is_continuous(n_values: int, n_columns: int, bins: int) -> bool:
    """Whether a swept parameter is summarised in quantile bins instead of value by value.

    Continuous: more distinct values ``n`` than bins, and ``n^2 > N`` for ``N``
    columns (its values average fewer columns each than there are values, as
    with one draw per attitude); a grid of a few values over many attitudes is not.
    """
    return n_values > bins and n_values * n_values > n_columns


def _nan_reduce(fn, values: np.ndarray) -> np.ndarray:
    """``fn`` over axis 1 that returns NaN quietly for all-NaN rows."""
    out = np.full(values.shape[0], np.nan)
    rows = ~np.all(np.isnan(values), axis=1)
    if rows.any():
        out[rows] = fn(values[rows], axis=1)
    return out


# --------------------------------------------------------------------------
# One chunk of runs
# --------------------------------------------------------------------------


def _run_metrics(
    scene,
    method,
    dt,
    n_steps,
    save_every,
    threshold,
    weights,
    k_R,
    k_O,
    R0,
    W0,
    pv=None,
    scalarize=False,
    run_key=None,
):
    """One run's statistics, as the scene's sweep hook takes them (`so3jax._sweep_hooks`).

    ``run_key``: the run's key for the scene's `SensorNoise` (`noise_key`), or ``None``
    for a scene without noise.
    """
    hook = sweep_hook(scene)
    if run_key is not None:
        scene = hook.with_noise_key(scene, run_key)
    return hook.run(
        scene, method, dt, n_steps, save_every, threshold, weights, k_R, k_O, R0, W0, pv, scalarize
    )


@_plan.jit
def _run_chunk(
    scene,
    method,
    dt,
    n_steps,
    save_every,
    threshold,
    weights,
    k_R,
    k_O,
    R0,
    W0,
    pv=None,
    scalarize=False,
    noise=None,
):
    """A chunk of runs, vmapped. ``noise``: ``(key, attitude)`` for a scene with sensor
    noise (the sweep's key, and each run's attitude index, `(B,)`: the run draws from
    ``noise_key(key, attitude)``), ``None`` otherwise (the program of a scene without)."""
    key, attitude = (None, None) if noise is None else noise
    fn = lambda a, b, c, d, e, i: _run_metrics(
        scene, method, dt, n_steps, save_every, threshold, weights, a, b, c, d, e, scalarize,
        None if i is None else noise_key(key, i),
    )  # fmt: skip
    return jax.vmap(fn)(k_R, k_O, R0, W0, pv, attitude)


#: The slot of an attitude's key that seeds its runs' sensor noise (`noise_key`); slots
#: 0, 1 and ``2 + k`` draw its attitude, its rate and parameter ``k``'s distribution.
NOISE_SLOT = 2**31 - 1


def sweep_scalarize(devices) -> bool:
    """Whether `so3jax.sweep` over ``devices`` runs the scalarized program by default (a
    TPU counts as a GPU; never with the ``"scalarize"`` pass off)."""
    platform = "cpu" if list(devices)[0].platform == "cpu" else "gpu"
    return current().on("scalarize") and dict(current().sweep_scalarize)[platform]


def sweep_chunk(devices, n_saved: int, itemsize: int) -> int:
    """Default runs per chunk of `so3jax.sweep` over ``devices``.

    The policy's chunk for the devices' platform, per device; on an accelerator at most
    as many runs as keep ``n_saved`` saved points of every run (48 numbers each, of
    ``itemsize`` bytes) within half the smallest device's memory (16 GiB where a device
    does not say), and at least the CPU's chunk. The peak memory of a seed chunk is
    about 34 numbers a saved point; 48 leaves room for a quadrotor's state.
    """
    devices = list(devices)
    policy = current()
    if devices[0].platform == "cpu":
        return policy.chunk("cpu") * len(devices)
    known = []  # a TPU counts as a GPU
    for d in devices:
        try:
            known.append((d.memory_stats() or {}).get("bytes_limit"))
        except Exception:  # a backend without memory statistics
            pass
    known = [x for x in known if x]
    budget = (min(known) if known else 16 * 2**30) // 2  # unknown: a 16 GiB device
    fits = budget // (n_saved * 48 * itemsize)
    return max(policy.chunk("cpu"), min(policy.chunk("gpu"), fits)) * len(devices)


def noise_key(key, attitude):
    """The `SensorNoise` key of the runs from attitude ``a`` of a sweep with key ``key``.

    ``fold_in(fold_in(key, a), NOISE_SLOT)``, ``NOISE_SLOT = 2**31 - 1``: it depends on
    the attitude alone, so every gain pair and every parameter combination run from
    attitude ``a`` reads the same noise (common random numbers, as for the attitudes),
    and it does not depend on the number of attitudes, the chunks or the devices.
    """
    return jax.random.fold_in(jax.random.fold_in(key, attitude), NOISE_SLOT)


def _sharded(x: np.ndarray, sharding) -> Array:
    """Place a host array on the mesh (each process supplies its own shards)."""
    return jax.make_array_from_callback(x.shape, sharding, lambda idx: x[idx])


def _to_host(tree):
    """Arrays on the host; shards on other processes are gathered (every process gets all)."""

    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            from jax.experimental import multihost_utils

            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(x)

    return jax.tree.map(one, tree)


def _from_process_0(data: bytes | None) -> bytes:
    """``data`` of process 0, on every process (a no-op with one process)."""
    if jax.process_count() == 1:
        return data
    from jax.experimental import multihost_utils

    first = jax.process_index() == 0
    n = int(multihost_utils.broadcast_one_to_all(np.int32(len(data) if first else 0)))
    buf = np.frombuffer(data, np.uint8) if first else np.zeros(n, np.uint8)
    return np.asarray(multihost_utils.broadcast_one_to_all(buf), np.uint8).tobytes()


def _shared_json(make: Callable[[], dict]) -> dict:
    """``make()`` run on process 0 only, its result (or its error) on every process."""
    out = None
    if jax.process_index() == 0:
        try:
            out = {"ok": make()}
        except (ValueError, OSError) as e:  # raised on every process, not only on process 0
            out = {"error": str(e), "type": type(e).__name__}
    out = json.loads(_from_process_0(None if out is None else json.dumps(out).encode()))
    if "error" in out:
        raise (ValueError if out["type"] == "ValueError" else OSError)(out["error"])
    return out["ok"]


# --------------------------------------------------------------------------
# The sweep
# --------------------------------------------------------------------------


def _as_key(key):
    if isinstance(key, int):
        return jax.random.key(key)
    try:
        jax.random.key_data(key)
    except Exception:
        raise ValueError(f"key must be a JAX PRNG key or an int seed, got {key!r}") from None
    return key


def initial_states(key, n: int, omega0_std: float = 0.0, dtype=None, Omega0=None):
    """Initial attitudes (uniform on SO(3)) and rates; sample ``i`` from ``fold_in(key, i)``.

    ``R0_i ~ Haar(SO(3))``, ``Omega0_i = Omega0 + omega0_std * N(0, I_3)``.

    **Arguments:**

    - `key`: a JAX PRNG key (or an int seed).
    - `n`: number of samples.
    - `omega0_std`: standard deviation of the random initial rate, rad/s.
    - `dtype`: float dtype.
    - `Omega0`: mean initial rate, shape `(3,)` (default zero).

    **Returns:** ``(R0, Omega0)`` of shapes `(n, 3, 3)` and `(n, 3)`; sample
    ``i`` does not depend on ``n``.
    """
    key = _as_key(key)
    n = _check_int(n, "n", 0)
    dtype = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    base = jnp.zeros(3, dtype) if Omega0 is None else jnp.asarray(Omega0, dtype)
    return _draw(key, base, jnp.asarray(omega0_std, dtype), n)


@functools.partial(jax.jit, static_argnums=3)
def _draw(key, Omega0, omega0_std, n: int):
    dtype = Omega0.dtype
    keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.arange(n))
    R0 = jax.vmap(lambda k: random_rotation(jax.random.fold_in(k, 0), dtype=dtype))(keys)
    noise = jax.vmap(lambda k: jax.random.normal(jax.random.fold_in(k, 1), (3,), dtype))(keys)
    return R0, Omega0 + omega0_std * noise


def _gain_pairs(k_R, k_Omega, grid: bool, allow_negative: bool = False):
    k_R = np.asarray(k_R, dtype=np.float64)
    k_O = np.asarray(k_Omega, dtype=np.float64)
    for k, name in ((k_R, "k_R"), (k_O, "k_Omega")):
        if k.ndim not in (1, 2) or k.shape[0] < 1 or (k.ndim == 2 and k.shape[1] != 3):
            raise ValueError(
                f"{name} must have shape (n,) (scalar gains) or (n, 3) (per-axis), got {k.shape}"
            )
        if not np.all(np.isfinite(k)):
            raise ValueError(f"{name} must be finite")
        if np.any(k < 0) and not allow_negative:
            raise ValueError(
                f"{name} must be >= 0 (negative gains destabilise the loop; pass "
                "allow_negative_gains=True to sweep them on purpose)"
            )
    if grid:
        if k_R.ndim != 1 or k_O.ndim != 1:
            raise ValueError("a grid sweep takes 1-D k_R and k_Omega; pass grid=False for pairs")
        a, b = np.meshgrid(k_R, k_O, indexing="ij")
        return a.reshape(-1), b.reshape(-1), (k_R.shape[0], k_O.shape[0])
    if k_R.shape != k_O.shape:
        raise ValueError(
            "with grid=False, k_R and k_Omega are pairs and need the same shape, "
            f"got {k_R.shape} and {k_O.shape}"
        )
    return k_R, k_O, None


def _fingerprint(config: dict, scene, method) -> str:
    h = hashlib.sha256(json.dumps(config, sort_keys=True).encode())
    for tree in (scene, method):
        arrays, static = eqx.partition(tree, eqx.is_array)
        h.update(repr(jax.tree.structure(arrays)).encode())
        h.update(repr(static).encode())
        for leaf in jax.tree.leaves(arrays):
            if jnp.issubdtype(leaf.dtype, jax.dtypes.prng_key):  # a `SensorNoise` key
                h.update(str(jax.random.key_impl(leaf)).encode())
                leaf = jax.random.key_data(leaf)
            leaf = np.asarray(leaf)
            h.update(str(leaf.dtype).encode() + leaf.tobytes())
    return h.hexdigest()


def sweep(
    scene,
    k_R,
    k_Omega,
    *,
    key=0,
    n_attitudes: int = 16,
    grid: bool = True,
    method: AbstractLieSolver | None = None,
    dt: float = 1e-2,
    n_steps: int = 1000,
    save_every: int = 1,
    omega0_std: float = 0.0,
    params: Mapping | None = None,
    param_grid: bool = True,
    threshold: float = 0.01,
    position_threshold: float = 0.05,
    weights: CostWeights | None = None,
    refine: int = 4,
    safety: float = SAFETY,
    allow_negative_gains: bool = False,
    chunk_size: int | None = None,
    results_dir: str | os.PathLike | None = None,
    overwrite: bool = False,
    devices=None,
    progress: bool = True,
    on_chunk: Callable[[int, int], None] | None = None,
    scalarize: bool | None = None,
) -> SweepResult:
    """Monte Carlo sweep of the geometric controller: gain pairs x random initial attitudes.

    Every gain pair ``g`` is run from every initial state ``i`` (``R0_i``
    uniform on SO(3), see `initial_states`), ``G x N`` runs of
    ``simulate(scene with (k_R[g], k_Omega[g]) and (R0_i, Omega0_i))``. The
    runs go through in chunks of `chunk_size` (vmapped, sharded over
    `devices`); memory is bounded by the chunk size. With `results_dir`, each
    finished chunk is saved at once (``chunk_NNNNN.npz``, written atomically)
    and a later call with the same arguments loads it instead of running it
    again: an interrupted sweep resumes where it stopped. A run that diverges
    is re-run right after its chunk at a step known to be stable for its gains
    (`stable_dt`, reached by halving ``dt`` with the saved points at the same
    times): if it is finite there it failed only numerically
    (`SweepResult.numerical`, statistics from that run), if it fails there the
    closed loop diverged (`SweepResult.diverged`, left out of the statistics).
    A `warnings.warn` says up front when ``dt`` is past the limit for some gains
    and which ``dt`` would be stable for all.

    **Arguments:**

    - `scene`: a tracking scene with the geometric controller, e.g. `scenes.seed()`;
      its reference, inertia and ``Rd0`` are kept, its gains and ``(R0, Omega0)`` replaced.
      Or a quadrotor (`scenes.quadrotor`, e.g. `scenes.quadrotor_recovery()`): its
      attitude gains ``k_R``, ``k_Omega`` are swept (``k_x``, ``k_v``, the vehicle,
      reference, ``x0``, ``v0`` and control period kept) from every initial attitude,
      upside-down ones included. Its statistics are taken against the commanded
      attitude (``Psi(R, Rc)``); a run settles when ``Psi < threshold`` *and*
      ``|e_x| < position_threshold``; its cost adds ``int |e_x|^2 dt`` to the
      weighted terms (``Psi(R, Rc)``, ``e_Omega`` against ``Omega_c``, ``M``); and
      `SweepResult.metrics` holds ``final_position_error``, ``max_position_error``,
      ``rms_position_error`` (m) and ``min_thrust_axis_up`` (the least cosine between
      thrust axis and up over the saved points: below 0, it flew upside down).
      With sampled control (``control_period``) the feedback sets no step limit
      (it is held over a step): a failed run is re-run at half the step, numerical
      if finite there (a fast spin the step did not resolve), diverged if not; a
      rotor lag ``tau`` limits the step to ``safety * stability_interval(method) *
      tau``. How `sweep` treats a scene is the scene's hook (``scene.sweep_hook()``,
      `so3jax._sweep_hooks`: its parameters, start, statistics and step limit).
    - `k_R`, `k_Omega`: gains, shape `(a,)` and `(b,)` (``grid=True``: all
      ``a * b`` pairs) or both `(G,)` / `(G, 3)` (``grid=False``: a list of pairs).
    - `key`: a JAX PRNG key or an int seed for the initial states, and for the sensor
      noise of a scene built with ``noise=SensorNoise(...)``: the runs from attitude
      ``a`` read the noise of key ``fold_in(fold_in(key, a), 2**31 - 1)`` (the scene's
      own noise key is not used). Every gain pair and every parameter combination from
      attitude ``a`` reads the same draws (common random numbers, as they start from the
      same attitude), so their differences are not sampling noise; different attitudes
      read independent noise. A run is reproduced by `simulate` of the scene started
      there with that key; it does not depend on the chunks, the devices or
      `n_attitudes`.
    - `n_attitudes`: ``N``, initial attitudes per gain pair.
    - `grid`: cross `k_R` with `k_Omega` (``True``) or pair them (``False``).
    - `method`: a Lie-group method (default `RKMK4()`).
    - `dt`, `n_steps`, `save_every`: as in `simulate` (statistics use saved points).
    - `omega0_std`: standard deviation of random initial rates (rad/s) added
      to the scene's ``Omega0``.
    - `params`: other scene parameters to vary, by name. An attitude scene takes
      ``inertia_scale`` (`(P,)` or `(P, 3)`, > 0, per axis), ``disturbance``
      (`(P, 3)`, a constant body torque in N m), ``Omega0`` (`(P, 3)`, initial
      rates), ``reference_amplitude`` (`(P,)`, a factor on the reference rate) and
      ``max_torque`` (`(P,)` or `(P, 3)`, > 0: the torque limit in N m per body
      axis, as `scenes.tracking`'s ``max_torque``; a scene without one gets it). A
      quadrotor takes ``Omega0``; ``thrust_max`` (`(P,)`, N per rotor) or
      ``thrust_to_weight`` (`(P,)`, ``4 thrust_max / (m g)``), which must let the
      rotors hover, with a scene built with ``rotors=so3jax.Rotors(...)``;
      ``time_constant`` (`(P,)`, > 0, the rotor lag in s; rotors built with a time
      constant, so that their thrusts are state); and ``wind_speed`` (`(P, 3)`, a
      constant mean wind in m/s, world frame; a scene with ``drag``). Either kind of
      scene built with ``noise=SensorNoise(...)`` takes ``noise_scale`` (`(P,)`,
      >= 0: a factor on all of its noise's standard deviations; 0 is the noise-free
      run, to round-off). Every combination runs from every initial attitude:
      ``N = P * n_attitudes`` columns, keyed by name in `SweepResult.params`. A value
      may instead be a distribution, a function ``key -> value``, drawn once per
      initial attitude. A wrong name, shape or value, or a parameter the scene cannot
      take, raises a ``ValueError`` naming it.
    - `param_grid`: cross the `params` arrays (``True``) or zip them (``False``:
      the same length, e.g. samples drawn from a distribution).
    - `threshold`: settling threshold on ``Psi = 1 - cos(angle)`` (0.01: 8.1 degrees).
    - `position_threshold`: a quadrotor's settling threshold on ``|e_x|``, in m.
    - `weights`: `CostWeights` of the integrated cost.
    - `refine`: at most this many halvings of ``dt`` to resolve a failed run
      (0: none; a failure is then diverged if ``dt`` is known stable, unresolved
      if not). A failure at a step known to be stable is confirmed once at half
      that step before it counts as diverged.
    - `safety`: factor on the linearised step limit (`stable_dt`).
    - `allow_negative_gains`: accept negative gains (a destabilising sign, on
      purpose); otherwise they raise ``ValueError``.
    - `chunk_size`: runs per chunk (rounded up to a multiple of the device count).
      ``None``: 1024 per device on CPU; on a GPU 65536 per device (a GPU takes about as
      long for a chunk of 1024 runs as for one of 65536), fewer where the chunk's saved
      points would fill more than half the device's memory; the runs are then spread
      evenly over the fewest chunks. With several processes, process 0's choice holds.
    - `results_dir`: folder for the chunk files (created; ``None``: keep in memory; with
      several processes, process 0 alone reads and writes it).
    - `overwrite`: discard chunk files of a different sweep in `results_dir`
      instead of raising.
    - `devices`: devices to shard each chunk over (default: all, `jax.devices()`;
      after `jax.distributed.initialize`, every process's devices: call `sweep`
      with the same arguments on every process, and each gets the whole result).
    - `progress`: show a tqdm progress bar over runs (runs/s, ETA, outcome counts).
    - `on_chunk`: called as ``on_chunk(index, n_chunks)`` after each chunk is computed
      (and saved).
    - `scalarize`: step each chunk as a program over scalar components
      (``simulate(..., scalarize=True)``) or as the array program (``False``): the
      same numbers to round-off. ``None`` (default) picks per platform: scalarized on a
      CPU (several times faster in batches, a few seconds more to compile), the array
      program on a GPU (both latency bound there; the array program compiles several
      times faster, so a sweep finishes sooner unless the same sweep is repeated
      dozens of times in one process; the engine policy's ``sweep_scalarize``).

    **Returns:** a `SweepResult`.
    """
    hook = sweep_hook(scene)
    hook.check(scene)
    if method is None:
        method = RKMK4()
    if not isinstance(method, AbstractLieSolver):
        raise TypeError(f"method must be a so3jax Lie-group method, got {method!r}")
    weights = _check_weights(weights)
    n_att = _check_int(n_attitudes, "n_attitudes", 1)
    n_steps = _check_int(n_steps, "n_steps", 1)
    save_every = _check_int(save_every, "save_every", 1)
    if n_steps % save_every:
        raise ValueError(f"n_steps ({n_steps}) must be a multiple of save_every ({save_every})")
    if chunk_size is not None:
        chunk_size = _check_int(chunk_size, "chunk_size", 1)
    dt = float(dt)
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be positive and finite, got {dt}")
    if getattr(scene, "control_period", None) is not None:  # traced inside the chunks
        scene.steps_per_hold(dt)  # sampled control: dt must divide the period
    threshold = float(threshold)
    if not (0 < threshold <= 2):
        raise ValueError(f"threshold must be in (0, 2] (Psi = 1 - cos(angle)), got {threshold}")
    position_threshold = float(position_threshold)
    if not (math.isfinite(position_threshold) and position_threshold > 0):
        raise ValueError(f"position_threshold must be > 0 (m), got {position_threshold}")
    omega0_std = float(omega0_std)
    if not (math.isfinite(omega0_std) and omega0_std >= 0):
        raise ValueError(f"omega0_std must be >= 0, got {omega0_std}")
    refine = _check_int(refine, "refine", 0)
    safety = float(safety)
    if not (0 < safety <= 1):
        raise ValueError(f"safety must be in (0, 1], got {safety}")
    key = _as_key(key)
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("devices must not be empty")

    dtype = scene.y0.R.dtype
    kr, ko, grid_shape = _gain_pairs(k_R, k_Omega, grid, bool(allow_negative_gains))
    G = kr.shape[0]
    arrays, dists = split_params(params)
    hook.accept(set(arrays) | set(dists))
    prows = check_params(arrays, bool(param_grid))
    P = next(iter(prows.values())).shape[0] if prows else 1
    drawn = draw(dists, key, n_att)
    scene = hook.prepare(scene, {**prows, **drawn})
    noisy = getattr(scene, "noise", None) is not None  # one noise key per run (`noise_key`)
    if noisy:  # the scene's own key is not used (nor fingerprinted): the runs' replace it
        scene = hook.with_noise_key(scene, key)
    run_threshold, position_threshold = hook.thresholds(threshold, position_threshold)
    # Column i = p * n_att + a: combination p of the parameter arrays, from attitude a
    # (distributions are sampled per attitude a).
    col_p, col_a = np.arange(P * n_att) // n_att, np.arange(P * n_att) % n_att
    col_params = {k: v[col_p] for k, v in prows.items()}
    col_params.update({k: v[col_a] for k, v in drawn.items()})
    st = hook.stable_dt(scene, method, kr, ko, safety, col_params, col_p.size)
    dt_stable = st.min(axis=1)
    _warn_step(method, dt, dt_stable, ko, refine)
    Omega_scene = hook.initial_rate(scene)
    R0a, W0a = initial_states(key, n_att, omega0_std, dtype, Omega_scene)
    R0, W0 = np.asarray(R0a)[col_a], np.asarray(W0a)[col_a]
    if "Omega0" in col_params:
        W0 = (W0 - np.asarray(Omega_scene) + col_params["Omega0"]).astype(dtype)
    pv_cols = {k: v.astype(dtype) for k, v in col_params.items() if k != "Omega0"}
    n_att = P * n_att  # columns
    stable_run = st.reshape(-1)
    n_runs = G * n_att
    n_dev = len(devices)
    chosen = scalarize is None  # the policy's choice, not the caller's: fall back silently
    if chosen:
        scalarize = sweep_scalarize(devices)
    if chunk_size is None:  # the fewest chunks of equal size, not full ones and a padded last
        n_saved, itemsize = n_steps // save_every + 1, jnp.dtype(dtype).itemsize
        # Every process must cut the same chunks: process 0's figure (from the memory of
        # the devices it can query) holds for all.
        cap = _shared_json(lambda: {"cap": sweep_chunk(devices, n_saved, itemsize)})["cap"]
        chunk_size = -(-n_runs // -(-n_runs // cap))
    chunk = min(chunk_size, n_runs)
    chunk = -(-chunk // n_dev) * n_dev
    n_chunks = -(-n_runs // chunk)

    folder, on_disk = None, set()
    if results_dir is not None:
        config = {
            "k_R": kr.tolist(),
            "k_Omega": ko.tolist(),
            "key": np.asarray(jax.random.key_data(key)).tolist(),
            "n_attitudes": n_att,
            "omega0_std": omega0_std,
            "params": {k: v.tolist() for k, v in col_params.items()},
            "param_grid": bool(param_grid),
            "dt": dt,
            "n_steps": n_steps,
            "save_every": save_every,
            "threshold": threshold,
            "position_threshold": position_threshold,
            "weights": [float(weights.psi), float(weights.omega), float(weights.effort)],
            "chunk": chunk,
            "refine": refine,
            "safety": safety,
            "format": 2,  # chunk files carry outcome and run_dt
        }
        folder = Path(results_dir)
        fingerprint = _fingerprint(config, scene, method)

        def existing() -> dict:
            _prepare_folder(folder, fingerprint, overwrite)
            names = [f"chunk_{c:05d}.npz" for c in range(n_chunks)]
            return {"chunks": [c for c, n in enumerate(names) if (folder / n).exists()]}

        # Process 0 owns the folder; the others learn from it which chunks to load.
        on_disk = set(_shared_json(existing)["chunks"])

    mesh = Mesh(np.asarray(devices), ("batch",))
    sharding = NamedSharding(mesh, PartitionSpec("batch"))
    g_idx = np.arange(n_runs) // n_att
    i_idx = np.arange(n_runs) % n_att

    def run(rows, level: int, size: int) -> dict:
        """Runs ``rows`` (padded to ``size`` by repeating the last) at ``dt / 2**level``."""
        rows = np.concatenate([rows, np.full(size - rows.size, rows[-1])])
        args = (
            kr[g_idx[rows]].astype(dtype),
            ko[g_idx[rows]].astype(dtype),
            R0[i_idx[rows]],
            W0[i_idx[rows]],
            {k: v[i_idx[rows]] for k, v in pv_cols.items()},
        )
        if noisy:  # each run's attitude index, from which its noise key is drawn
            args = args + (col_a[i_idx[rows]].astype(np.int32),)
        args = jax.tree.map(lambda a: _sharded(a, sharding), args)
        noise = (key, args[5]) if noisy else None
        args = args[:5]
        f = 2**level
        with warnings.catch_warnings():
            if chosen:  # a step the scalarizer does not take (random draws) runs as arrays
                warnings.filterwarnings("ignore", "scalarize: .*running the array program")
            out = _run_chunk(
                scene,
                method,
                dt / f,
                n_steps * f,
                save_every * f,
                run_threshold,
                weights,
                *args,
                bool(scalarize),
                *(() if noise is None else (noise,)),  # (a scene without noise: the same call)
            )
        return _to_host(out)

    parts: list[dict] = []
    bar = None
    counts = {"numerical": 0, "diverged": 0, "unresolved": 0}
    if progress and jax.process_index() == 0:
        from tqdm.auto import tqdm

        bar = tqdm(total=n_runs, desc="sweep", unit="run", smoothing=0.1)
    t_start, computed = time.perf_counter(), 0
    try:
        for c in range(n_chunks):
            lo, hi = c * chunk, min((c + 1) * chunk, n_runs)
            path = None if folder is None else folder / f"chunk_{c:05d}.npz"
            loaded = path is not None and c in on_disk
            if loaded:
                first = jax.process_index() == 0
                data = _from_process_0(path.read_bytes() if first else None)
                out = _load_chunk(io.BytesIO(data), hi - lo, path)
            else:
                # Pad the last chunk by repeating its last run: one compiled shape for all.
                out = run(np.arange(lo, hi), 0, chunk)
                out = {k: v[: hi - lo] for k, v in out.items()}
                out = _resolve(
                    out, np.arange(lo, hi), stable_run[lo:hi], dt, refine, chunk, n_dev, run
                )
                if path is not None and jax.process_index() == 0:
                    tmp = path.with_name(path.stem + ".tmp.npz")
                    np.savez(tmp, **out)
                    os.replace(tmp, path)
                computed += hi - lo
            parts.append(out)
            for name, code in (
                ("numerical", NUMERICAL),
                ("diverged", DIVERGED),
                ("unresolved", UNRESOLVED),
            ):
                counts[name] += int(np.sum(out["outcome"] == code))
            if bar is not None:
                elapsed = time.perf_counter() - t_start
                rate = computed / elapsed if elapsed > 0 else 0.0
                bar.set_postfix({"runs/s": f"{rate:.0f}", **counts}, refresh=False)
                bar.update(hi - lo)
            if on_chunk is not None and not loaded:
                on_chunk(c, n_chunks)
    finally:
        if bar is not None:
            bar.close()

    runs = {k: np.concatenate([p[k] for p in parts]).reshape(G, n_att) for k in RUN_FIELDS}
    metrics = {
        k: np.concatenate([p[k] for p in parts]).reshape(G, n_att)
        for k in parts[0]
        if k not in RUN_FIELDS
    }
    return SweepResult(
        k_R=kr,
        k_Omega=ko,
        grid_shape=grid_shape,
        R0=R0,
        Omega0=W0,
        stable_dt=dt_stable,
        threshold=threshold,
        dt=dt,
        n_steps=n_steps,
        save_every=save_every,
        refine=refine,
        params=col_params,
        metrics=metrics,
        position_threshold=position_threshold,
        scalarize=bool(scalarize),
        **runs,
    )


def _warn_step(method, dt: float, dt_stable: np.ndarray, k_Omega: np.ndarray, refine: int):
    """Warn when ``dt`` is past the method's stability limit for some gain pairs."""
    if np.isnan(dt_stable).any():
        warnings.warn(
            f"the stability limit of {method.name} is not known: runs that fail are re-run "
            f"at halved steps (at most {refine} halvings) and reported numerical if that "
            "resolves them, unresolved otherwise, never diverged",
            stacklevel=3,
        )
        return
    beyond = dt > dt_stable
    if not beyond.any():
        return
    k_O = np.asarray(k_Omega).reshape(len(k_Omega), -1).max(axis=1)
    need = _levels_to_stable(dt, dt_stable)
    over = need > refine
    budget = (
        f"; {int(over.sum())} of them need more than {refine} halvings (refine), and their "
        "failures will be reported unresolved"
        if over.any()
        else ""
    )
    warnings.warn(
        f"dt = {dt:g} is beyond the stability limit of {method.name} for {int(beyond.sum())} "
        f"of {beyond.size} gain pairs (k_Omega >= {k_O[beyond].min():.3g}, linearised closed "
        f"loop): runs that fail there are re-run at smaller steps and reported as numerical"
        f"{budget}. dt <= {np.min(dt_stable):.3g} is stable for every pair.",
        stacklevel=3,
    )


def _levels_to_stable(dt: float, dt_stable: np.ndarray) -> np.ndarray:
    """Smallest ``m >= 0`` with ``dt / 2**m <= dt_stable`` (0 where the limit is unknown)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        m = np.ceil(np.log2(dt / dt_stable) - 1e-12)
    return np.where(np.isnan(m), 0, np.maximum(m, 0)).astype(np.int64)


def _bucket(n: int, chunk: int, n_dev: int) -> int:
    """A padded batch size for ``n`` re-runs: a power of two (few compiled shapes),
    a multiple of the device count, at most the chunk."""
    b = min(chunk, 1 << max(0, (n - 1).bit_length()))
    return min(chunk, -(-b // n_dev) * n_dev)


def _resolve(out: dict, rows, stable, dt, refine: int, chunk: int, n_dev: int, run):
    """Classify the runs of a chunk; re-run the failed ones at smaller, stable steps.

    A failed run goes to level ``m = max(1, m0)``, ``m0`` the halvings that make
    the step known to be stable for its gains (unknown stability: every level in
    turn). Finite there: numerical, its statistics replaced. Failed at a known
    stable step: diverged. Past ``refine`` halvings: unresolved.
    """
    n = rows.size
    failed = out["status_code"] != OK
    outcome = np.where(failed, UNRESOLVED, FINITE).astype(np.int32)
    run_dt = np.where(failed, np.nan, dt)
    out = {k: np.array(v) for k, v in out.items()}
    m0 = _levels_to_stable(dt, stable)
    if refine == 0:
        hit = failed & (dt <= stable)
        outcome[hit], run_dt[hit] = DIVERGED, dt
    pending = np.flatnonzero(failed) if refine > 0 else np.zeros(0, int)
    for level in range(1, refine + 1):
        sel = pending[np.maximum(m0[pending], 1) <= level]
        if sel.size == 0:
            continue
        dt_level = dt / 2**level
        res = run(rows[sel], level, _bucket(sel.size, chunk, n_dev))
        res = {k: v[: sel.size] for k, v in res.items()}
        ok = res["status_code"] == OK
        for k in out:
            if k not in ("status_code", "fail_step"):
                out[k][sel[ok]] = res[k][ok]
        outcome[sel[ok]], run_dt[sel[ok]] = NUMERICAL, dt_level
        div = ~ok & (dt_level <= stable[sel])
        outcome[sel[div]], run_dt[sel[div]] = DIVERGED, dt_level
        pending = np.setdiff1d(pending, sel[ok | div])
    out["outcome"], out["run_dt"] = outcome, run_dt
    assert all(v.shape[0] == n for v in out.values())
    return out


def _prepare_folder(folder: Path, fingerprint: str, overwrite: bool) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    meta = folder / "sweep.json"
    if meta.exists():
        old = json.loads(meta.read_text()).get("fingerprint")
        if old == fingerprint:
            return folder
        if not overwrite:
            raise ValueError(
                f"results_dir {str(folder)!r} holds the chunks of a different sweep (or of "
                "an older so3jax); "
                "use another folder, or overwrite=True to discard them"
            )
    for stale in folder.glob("chunk_*.npz"):
        stale.unlink()
    meta.write_text(json.dumps({"fingerprint": fingerprint}))
    return folder


def _load_chunk(file, n: int, path: Path) -> dict:
    with np.load(file) as z:
        missing = [k for k in RUN_FIELDS if k not in z.files]
        if missing:
            raise ValueError(
                f"{path} was written by an older so3jax (no {', '.join(missing)}); "
                "use another results_dir, or delete its chunk files to recompute them"
            )
        out = {k: z[k] for k in z.files}
    if any(v.shape[0] != n for v in out.values()):
        raise ValueError(f"{path} has the wrong number of runs; delete it to recompute it")
    return out
