"""The ambient baseline: the same scenes integrated by diffrax in R^9 x R^n.

A Lie-group method moves ``R`` along the group. The baseline forgets the group:
it treats every rotation of the state as a free ``3 x 3`` matrix and integrates

    R_i' = R_i hat(xi_i),   x' = dx,   (xi, dx) = scene.vector_field(t, (R, x))

with an off-the-shelf Runge–Kutta method, so ``R^T R = I`` holds only to the
accuracy of the method (and drifts over long runs). This is what one gets from a
general-purpose ODE solver, and the yardstick of the benchmarks.

Two modes:

- *fixed step* (pass ``dt`` and ``n_steps``): the solver's ``step`` under
  `jax.lax.scan`, exactly like `simulate`; ``project=True`` replaces ``R`` by
  its nearest rotation after every step (and re-evaluates the first stage of
  FSAL methods, since the state moved).
- *adaptive* (pass ``t1``): `diffrax.diffeqsolve` with a `diffrax.PIDController`.
  ``project=True`` wraps the solver so that the end point of *every attempted
  step* is projected before the controller sees it (and the first stage is
  re-evaluated, no FSAL); the error estimate is that of the unprojected step.
  Saved points between steps come from the solver's dense output and are
  projected too. Projecting the saved points only would be a different (and
  weaker) thing: the drift would still feed back into the dynamics.
"""

from __future__ import annotations

from typing import ClassVar

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from ._engine import plan as _plan
from ._scene import Scene
from ._so3 import _hat, _is_concrete, _mm, _project
from ._state import LieState, all_finite
from ._trajectory import (
    NONFINITE,
    OK,
    Status,
    Trajectory,
    _check_dt,
    _check_int,
    _nan_unless,
    _trajectory,
    input_code,
    status_from_diffrax,
)
from ._types import Array

# The classic Runge–Kutta method (Kutta 1901), which diffrax does not ship. It has
# no embedded pair (zero error weights), so it is fixed-step only.
_RK4_TABLEAU = diffrax.ButcherTableau(
    c=np.array([0.5, 0.5, 1.0]),
    b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
    b_error=np.zeros(4),
    a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
)


class RK4(diffrax.AbstractERK):
    """The classic fourth-order Runge–Kutta method as a diffrax solver (fixed step).

    ``k1 = f(y), k2 = f(y + h k1/2), k3 = f(y + h k2/2), k4 = f(y + h k3)``,
    ``y1 = y + h (k1 + 2 k2 + 2 k3 + k4) / 6``.

    References: W. Kutta, Z. Math. Phys. 46 (1901) 435–453.
    """

    tableau: ClassVar[diffrax.ButcherTableau] = _RK4_TABLEAU
    interpolation_cls: ClassVar = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

    def order(self, terms):
        return 4


class _ProjectedSolver(diffrax.AbstractAdaptiveSolver, diffrax.AbstractWrappedSolver):
    """Wraps a solver: every step ends on the group (nearest rotation of each ``R``)."""

    solver: diffrax.AbstractSolver

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def interpolation_cls(self):
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    def order(self, terms):
        return self.solver.order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        # made_jump=True: the state was moved by the projection, so an FSAL method
        # must not reuse the last stage of the previous step.
        y1, y_error, dense_info, solver_state, result = self.solver.step(
            terms, t0, t1, y0, args, solver_state, True
        )
        return _project_state(y1), y_error, dense_info, solver_state, result

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)


#: Solvers by name: (constructor, adaptive?).
SOLVERS = {
    "tsit5": (diffrax.Tsit5, True),
    "dopri5": (diffrax.Dopri5, True),
    "dopri8": (diffrax.Dopri8, True),
    "rk4": (RK4, False),
}


def _project_state(y: LieState) -> LieState:
    return LieState(_project(y.R), y.x)


def _ambient_field(t, y: LieState, scene: Scene) -> LieState:
    """``(R hat(xi), dx)``: the scene's field written in the ambient coordinates."""
    f = scene.vector_field(t, y)
    return LieState(_mm(y.R, _hat(f.xi)), f.dx)


def _has_jump(scene: Scene) -> bool:
    """Whether ``scene.jump`` does anything (its jaxpr is not the identity)."""
    y0 = scene.y0
    closed = jax.make_jaxpr(scene.jump)(jnp.zeros((), y0.R.dtype), y0)
    jaxpr = closed.jaxpr
    return bool(jaxpr.eqns) or list(jaxpr.outvars) != list(jaxpr.invars[1:])


def _evals_per_step(solver, fresh_first_stage: bool) -> tuple[int, int]:
    """(evaluations per attempted step, evaluations at start) from the tableau; -1 if unknown."""
    tab = getattr(solver, "tableau", None)
    if tab is None:
        return -1, 0
    if tab.fsal and not fresh_first_stage:
        return tab.num_stages - 1, 1
    return tab.num_stages, 1 if tab.fsal else 0


def _get_solver(solver):
    if isinstance(solver, str):
        key = solver.lower()
        if key not in SOLVERS:
            raise ValueError(
                f"solver must be one of {sorted(SOLVERS)} or a diffrax solver, got {solver!r}"
            )
        cls, adaptive = SOLVERS[key]
        return cls(), adaptive
    if isinstance(solver, diffrax.AbstractSolver):
        return solver, isinstance(solver, diffrax.AbstractAdaptiveSolver) and not isinstance(
            solver, RK4
        )
    raise ValueError(f"solver must be one of {sorted(SOLVERS)} or a diffrax solver, got {solver!r}")


def _positive(value, name: str, dtype) -> Array:
    v = jnp.asarray(value, dtype=dtype)
    if v.shape != ():
        raise ValueError(f"{name} must be a scalar, got shape {v.shape}")
    if _is_concrete(v) and not (bool(jnp.isfinite(v)) and float(v) > 0):
        raise ValueError(f"{name} must be positive and finite, got {float(v)}")
    return v


def simulate_ambient(
    scene: Scene,
    solver: str | diffrax.AbstractSolver = "tsit5",
    t1: float | Array | None = None,
    *,
    dt: float | Array | None = None,
    n_steps: int | None = None,
    save_every: int = 1,
    rtol: float | Array = 1e-8,
    atol: float | Array = 1e-8,
    dt0: float | Array | None = None,
    n_save: int = 101,
    saveat_ts: Array | None = None,
    max_steps: int = 100_000,
    project: bool = False,
    t0: float | Array = 0.0,
    adjoint: diffrax.AbstractAdjoint | None = None,
) -> Trajectory:
    """Integrate a scene with diffrax in the ambient space (rotations as free 3x3 matrices).

    ``R_i' = R_i hat(xi_i)``, ``x' = dx`` for the scene's field ``(xi, dx)``; no
    group structure, so ``||R^T R - I||`` drifts unless ``project=True``.

    Pass ``dt`` and ``n_steps`` for fixed steps (under `jax.lax.scan`, like
    `simulate`), or ``t1`` for adaptive steps with a `diffrax.PIDController`.
    Works under `jit`, `vmap` and `grad` (adaptive runs differentiate through
    diffrax's adjoint, `diffrax.RecursiveCheckpointAdjoint` by default).

    **Arguments:**

    - `scene`: a scene, e.g. `scenes.free_body(...)`.
    - `solver`: ``"tsit5"``, ``"dopri5"``, ``"dopri8"`` (adaptive or fixed),
      ``"rk4"`` (classic RK4, fixed step only), or a diffrax solver instance.
    - `t1`: final time (adaptive mode).
    - `dt`, `n_steps`, `save_every`: step size, number of steps and saving
      stride (fixed-step mode; ``n_steps`` a multiple of ``save_every``).
    - `rtol`, `atol`: tolerances of the step-size controller (adaptive mode).
    - `dt0`: initial step (adaptive mode; ``None`` lets diffrax choose).
    - `n_save`: number of equally spaced saved times in ``[t0, t1]`` (>= 2;
      adaptive mode), unless `saveat_ts` is given.
    - `saveat_ts`: increasing saved times in ``[t0, t1]``, shape `(n,)`, the
      first one ``t0`` (adaptive mode).
    - `max_steps`: most steps an adaptive run may take (then it is flagged).
    - `project`: replace every ``R`` by its nearest rotation after every step.
    - `t0`: initial time.
    - `adjoint`: a diffrax adjoint for adaptive runs.

    **Returns:** a `Trajectory` (as from `simulate`), whose `extras` also hold
    ``num_steps``, ``num_accepted_steps``, ``num_rejected_steps`` and
    ``num_fevals`` (vector-field evaluations, counted from the tableau; -1 for
    a solver without one). The status code is 1 when the state stopped being
    finite or diffrax failed (e.g. ``max_steps`` reached); the status step is
    then the number of accepted steps.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a so3jax scene, got {type(scene).__name__}")
    solver, adaptive_ok = _get_solver(solver)
    if not isinstance(project, bool):
        raise ValueError(f"project must be True or False, got {project!r}")
    dtype = scene.y0.R.dtype
    t0 = jnp.asarray(t0, dtype=dtype)
    if dt is not None:
        if t1 is not None:
            raise ValueError("pass either dt and n_steps (fixed step) or t1 (adaptive), not both")
        if n_steps is None:
            raise ValueError("fixed-step mode (dt given) needs n_steps")
        n_steps = _check_int(n_steps, "n_steps", 1)
        save_every = _check_int(save_every, "save_every", 1)
        if n_steps % save_every:
            raise ValueError(f"n_steps ({n_steps}) must be a multiple of save_every ({save_every})")
        dt = _check_dt(dt, dtype)
        scene = scene.for_step(dt, t0)
        return _fixed(scene, solver, dt, t0, n_steps // save_every, save_every, project)

    if t1 is None:
        raise ValueError("pass t1 (adaptive steps) or dt and n_steps (fixed steps)")
    if n_steps is not None:
        raise ValueError("n_steps is for fixed steps: pass dt too, or drop n_steps")
    if not adaptive_ok:
        raise ValueError(
            f"solver {type(solver).__name__} has no error estimate: pass dt and n_steps"
        )
    if _has_jump(scene):
        raise ValueError(
            "adaptive steps do not support scenes with a discrete jump; pass dt and n_steps"
        )
    t1 = jnp.asarray(t1, dtype=dtype)
    if t1.shape != ():
        raise ValueError(f"t1 must be a scalar, got shape {t1.shape}")
    if _is_concrete(t1) and _is_concrete(t0) and not float(t1) > float(t0):
        raise ValueError(f"t1 must be greater than t0 = {float(t0)}, got {float(t1)}")
    rtol = _positive(rtol, "rtol", dtype)
    atol = _positive(atol, "atol", dtype)
    if dt0 is not None:
        dt0 = _positive(dt0, "dt0", dtype)
    max_steps = _check_int(max_steps, "max_steps", 1)
    if saveat_ts is None:
        n_save = _check_int(n_save, "n_save", 2)
        ts = t0 + (t1 - t0) * jnp.linspace(0.0, 1.0, n_save, dtype=dtype)
    else:
        ts = jnp.asarray(saveat_ts, dtype=dtype)
        if ts.ndim != 1 or ts.shape[0] < 1:
            raise ValueError(f"saveat_ts must be a non-empty 1-D array, got shape {ts.shape}")
        if _is_concrete(ts) and bool(jnp.any(jnp.diff(ts) < 0)):
            raise ValueError("saveat_ts must be non-decreasing")
    if adjoint is None:
        adjoint = diffrax.RecursiveCheckpointAdjoint()
    return _adaptive(scene, solver, t0, t1, ts, rtol, atol, dt0, max_steps, project, adjoint)


@_plan.jit
def _fixed(scene, solver, dt, t0, n_save: int, save_every: int, project: bool) -> Trajectory:
    term = diffrax.ODETerm(_ambient_field)
    y0 = scene.y0
    fresh = project or _has_jump(scene)
    made_jump = jnp.array(fresh)
    state0 = solver.init(term, t0, t0 + dt, y0, scene)
    nan_obs = jax.tree.map(lambda a: jnp.full_like(a, jnp.nan), scene.observe(t0, y0))

    def one_step(carry, _):
        y, state, k, code, bad = carry
        t = t0 + k * dt
        y1, _, _, state1, result = solver.step(term, t, t + dt, y, scene, state, made_jump)
        if project:
            y1 = _project_state(y1)
        y1 = scene.jump(t + dt, y1)
        good = all_finite(y1) & (result == diffrax.RESULTS.successful)
        newly = (code == OK) & ~good
        code = jnp.where(newly, NONFINITE, code)
        bad = jnp.where(newly, k, bad)
        keep = code == OK
        y, state = jax.tree.map(
            lambda new, old: jnp.where(keep, new, old), (y1, state1), (y, state)
        )
        return (y, state, k + 1, code, bad), None

    def save_block(carry, _):
        carry, _ = jax.lax.scan(one_step, carry, None, length=save_every)
        y, _, k, code, _ = carry
        t = t0 + k * dt
        obs = scene.observe(t, y)
        obs = jax.tree.map(lambda a, n: jnp.where(code == OK, a, n), obs, nan_obs)
        return carry, (t, obs)

    i32 = jnp.int32
    code0 = input_code(scene, dt, list(y0.R), y0.x)
    init = (y0, state0, jnp.array(0, i32), code0, jnp.array(-1, i32))
    (y, _, k, code, bad), (ts, obs) = jax.lax.scan(save_block, init, None, length=n_save)
    obs0 = _nan_unless(code0 == OK, scene.observe(t0, y0))
    t = jnp.concatenate([t0[None], ts])
    obs = jax.tree.map(lambda a0, a: jnp.concatenate([a0[None], a]), obs0, obs)
    per_step, at_start = _evals_per_step(solver, fresh)
    n_steps = n_save * save_every
    stats = {
        "num_steps": jnp.array(n_steps, i32),
        "num_accepted_steps": jnp.array(n_steps, i32),
        "num_rejected_steps": jnp.array(0, i32),
        "num_fevals": jnp.array(per_step * n_steps + at_start if per_step >= 0 else -1, i32),
    }
    return _trajectory(t, {**obs, **stats}, Status(code=code, step=bad), y)


@_plan.jit
def _adaptive(scene, solver, t0, t1, ts, rtol, atol, dt0, max_steps: int, project: bool, adjoint):
    term = diffrax.ODETerm(_ambient_field)
    inner = _ProjectedSolver(solver) if project else solver
    sol = diffrax.diffeqsolve(
        term,
        inner,
        t0,
        t1,
        dt0,
        scene.y0,
        args=scene,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        max_steps=max_steps,
        throw=False,
        adjoint=adjoint,
    )
    ys = sol.ys
    if project:
        ys = _project_state(ys)
    rows_ok = jax.vmap(all_finite)(ys)
    # Rows past a failure are not finite (diffrax fills them with inf): NaN them,
    # and restart from the last good one.
    idx = jnp.arange(ts.shape[0])
    last = jnp.max(jnp.where(rows_ok, idx, 0))
    y = jax.tree.map(lambda a: a[last], ys)
    obs = jax.vmap(scene.observe)(sol.ts, ys)
    obs = jax.tree.map(
        lambda a: jnp.where(rows_ok.reshape((-1,) + (1,) * (a.ndim - 1)), a, jnp.nan), obs
    )
    i32 = jnp.int32
    n_acc = sol.stats["num_accepted_steps"].astype(i32)
    status = status_from_diffrax(sol.result, jnp.all(rows_ok), n_acc)
    per_step, at_start = _evals_per_step(solver, project)
    n_steps = sol.stats["num_steps"].astype(i32)
    initial = 0 if dt0 is not None else 2  # diffrax's initial step selection: two evaluations
    stats = {
        "num_steps": n_steps,
        "num_accepted_steps": n_acc,
        "num_rejected_steps": sol.stats["num_rejected_steps"].astype(i32),
        "num_fevals": (per_step * n_steps + at_start + initial)
        if per_step >= 0
        else -1 + 0 * n_steps,
    }
    return _trajectory(sol.ts, {**obs, **stats}, status, y)
