"""Adaptive Lie-group stepping: `simulate` with tolerances instead of a step size.

An embedded RKMK pair (`RKMK45`, `RKMKTsit5`, `RKMK32`) runs as a diffrax solver
(`diffrax_solver`) under a `diffrax.PIDController`: the step size follows the
error estimate taken in the Lie algebra, every rotation stays on SO(3), and the
saved points between steps come from the pair's dense output on the group.

Derivatives (default ``adjoint=None``) hang on one ``jax.custom_jvp``, as the
fixed-step engine's do (`so3jax._engine`): through at most
the engine policy's ``forward_jacobian_max`` differentiated scalars (two gains, six
per-axis gains) the run computes its value and its Jacobian in one pass, JAX's
``jvp`` of the run through `diffrax.ForwardMode` with the unit tangents batched
over one primal; the tangent is that Jacobian times the input tangent, which JAX
transposes for ``grad``. Through more scalars, forward mode is the same ``jvp``
and reverse mode `diffrax.RecursiveCheckpointAdjoint`'s backward pass, joined by
``jax.custom_derivatives.linear_call``. Both are derivatives of the same
discretised run (diffrax holds the step sizes constant to autodiff), equal to
round-off. Second derivatives through a few scalars differentiate the one-pass
Jacobian again; it is a while loop, which JAX differentiates in forward mode only, so
reverse mode over it (``jacrev`` of ``jacfwd``, ``grad`` of a gradient's norm) transposes
its ``jvp`` by columns (`so3jax._engine.derivatives.ForwardColumns`).
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from ._engine import derivatives, plan as _plan, policy
from ._integrators import AbstractLieSolver
from ._integrators._diffrax import DiffraxLieAdaptiveSolver, diffrax_solver, lie_term
from ._scene import Scene
from ._so3 import _is_concrete
from ._state import all_finite
from ._trajectory import (
    Trajectory,
    _check_int,
    _trajectory,
    input_code,
    mark_bad_input,
    status_from_diffrax,
)
from ._types import Array

#: Default number of saved points (equally spaced, both ends included).
DEFAULT_N_SAVE = 101


def _positive_scalar(value, name: str, dtype) -> Array:
    v = jnp.asarray(value, dtype=dtype)
    if v.shape != ():
        raise ValueError(f"{name} must be a positive scalar, got shape {v.shape}")
    if _is_concrete(v) and not (bool(jnp.isfinite(v)) and float(v) > 0):
        raise ValueError(f"{name} must be positive and finite, got {float(v)}")
    return v


def _save_times(saveat, t0, t1, dtype) -> Array:
    if saveat is None:
        saveat = DEFAULT_N_SAVE
    if isinstance(saveat, int) and not isinstance(saveat, bool):
        n = _check_int(saveat, "saveat", 2)
        return t0 + (t1 - t0) * jnp.linspace(0.0, 1.0, n, dtype=dtype)
    ts = jnp.asarray(saveat, dtype=dtype)
    if ts.ndim != 1 or ts.shape[0] < 1:
        raise ValueError(
            "saveat must be a number of equally spaced points (int >= 2) or a non-empty "
            f"1-D array of times, got shape {ts.shape}"
        )
    if _is_concrete(ts) and _is_concrete(t0) and _is_concrete(t1):
        if bool(jnp.any(jnp.diff(ts) < 0)):
            raise ValueError("saveat times must be non-decreasing")
        if float(ts[0]) < float(t0) or float(ts[-1]) > float(t1):
            raise ValueError(
                f"saveat times must lie in [t0, t1] = [{float(t0)}, {float(t1)}], got "
                f"[{float(ts[0])}, {float(ts[-1])}]"
            )
    return ts


def simulate_adaptive(
    scene: Scene,
    method: AbstractLieSolver,
    t1: float | Array,
    rtol: float | Array | None = None,
    atol: float | Array | None = None,
    *,
    t0: float | Array = 0.0,
    saveat: int | Array | None = None,
    dt0: float | Array | None = None,
    max_steps: int = 4096,
    adjoint: diffrax.AbstractAdjoint | None = None,
) -> Trajectory:
    """Integrate a scene with an adaptive embedded RKMK pair (diffrax's step control).

    ``R_{n+1} = R_n exp(u_high)`` with ``h_n`` chosen by a
    `diffrax.PIDController` so that the algebra error ``|u_high - u_low|`` (and
    the vector-part error) stays below ``atol + rtol |y|``; usually called as
    ``simulate(scene, RKMK45(), t1=..., rtol=..., atol=...)``. Works under
    `jit`, `vmap`, `grad` and `jacfwd` (see `adjoint`).

    **Arguments:**

    - `scene`: a scene, e.g. `scenes.seed()`. Scenes with a discrete `jump`
      map (hybrid controllers) need fixed steps.
    - `method`: an embedded pair: `RKMK45()`, `RKMKTsit5()` (fewest steps at a
      given accuracy) or `RKMK32()` (loose tolerances).
    - `t1`: final time (> ``t0``).
    - `rtol`, `atol`: relative and absolute tolerances (> 0); one may be left
      out, it then equals the other.
    - `t0`: initial time.
    - `saveat`: number of equally spaced saved points (int >= 2, both ends
      included; default 101) or an increasing 1-D array of times in
      ``[t0, t1]``. Points between steps come from the dense output, on the
      group.
    - `dt0`: initial step (default: diffrax's heuristic).
    - `max_steps`: most steps (accepted + rejected); then the run is flagged.
    - `adjoint`: a diffrax adjoint for JAX to differentiate through. Default:
      the engine's choice (module docstring): through at most 8 differentiated
      scalars the one-pass Jacobian (`diffrax.ForwardMode` with the unit
      tangents batched over one run), for ``grad`` and ``jacfwd`` alike;
      through more, `diffrax.ForwardMode` for forward mode and
      `diffrax.RecursiveCheckpointAdjoint` for reverse mode.

    **Returns:** a `Trajectory` at the saved times whose `extras` also hold
    ``num_steps``, ``num_accepted_steps``, ``num_rejected_steps`` and
    ``num_fevals`` (vector-field evaluations, counted from the tableau). The
    status code is 3 when ``max_steps`` ran out before ``t1`` and 1 when the state
    stopped being finite or diffrax failed otherwise; its step is then the number of
    accepted steps, and the saved points not reached are NaN. Under ``jit`` / ``vmap``,
    input that was bad before the first step has its own code (`Status`).

    References: H. Munthe-Kaas, Appl. Numer. Math. 29 (1999) 115–127;
    E. Hairer, S. P. Nørsett, G. Wanner, *Solving Ordinary Differential
    Equations I*, 2nd ed., sec. II.4 (step-size control).
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a so3jax scene, got {type(scene).__name__}")
    if not isinstance(method, AbstractLieSolver):
        raise TypeError(
            f"method must be a so3jax Lie-group method (e.g. so3jax.RKMK45()), got {method!r}"
        )
    solver = diffrax_solver(method)
    if not isinstance(solver, DiffraxLieAdaptiveSolver):
        raise ValueError(
            "adaptive steps (rtol/atol given) need a method with an embedded error "
            f"estimate: so3jax.RKMK45(), RKMKTsit5() or RKMK32(), got {method!r}; or pass dt "
            "and n_steps for fixed steps"
        )
    if scene.jump(jnp.asarray(0.0), scene.y0) is not scene.y0:
        raise ValueError(
            "adaptive steps do not support scenes with a discrete jump map (hybrid "
            "controllers); pass dt and n_steps for fixed steps"
        )
    if rtol is None and atol is None:
        raise ValueError("adaptive steps need rtol and/or atol")
    dtype = scene.y0.R.dtype
    rtol = _positive_scalar(atol if rtol is None else rtol, "rtol", dtype)
    atol = _positive_scalar(rtol if atol is None else atol, "atol", dtype)
    t0 = jnp.asarray(t0, dtype=dtype)
    t1 = jnp.asarray(t1, dtype=dtype)
    if t0.shape != () or t1.shape != ():
        raise ValueError(f"t0 and t1 must be scalars, got shapes {t0.shape} and {t1.shape}")
    if _is_concrete(t0) and _is_concrete(t1) and not float(t1) > float(t0):
        raise ValueError(f"t1 must be greater than t0 = {float(t0)}, got {float(t1)}")
    ts = _save_times(saveat, t0, t1, dtype)
    if dt0 is not None:
        dt0 = _positive_scalar(dt0, "dt0", dtype)
    max_steps = _check_int(max_steps, "max_steps", 1)
    args = (scene, solver, t0, t1, ts, rtol, atol, dt0)
    if adjoint is not None:
        traj = _simulate_adaptive(*args, max_steps, adjoint)
    else:
        traj = _simulate_default(args, max_steps)
    if all(_is_concrete(a) for a in jax.tree.leaves((scene, dt0))):
        return traj  # concrete input was checked eagerly
    # Traced input (the caller's jit / vmap): a bad value is a status, as with fixed steps.
    one = jnp.ones((), dtype)
    code0 = input_code(scene, one if dt0 is None else dt0, list(scene.y0.R), scene.y0.x)
    return mark_bad_input(traj, code0)


@_plan.jit
def _simulate_default(args, max_steps: int):
    """The run with the engine's derivatives (module docstring); jitted, so that an
    eager call pays for building them once."""
    scene, t0 = args[0], args[2]
    if _closes_over_tracers(scene, t0):
        # A custom_jvp cannot differentiate through values its function closes
        # over; JAX's own autodiff can.
        return _simulate_adaptive(*args, max_steps, diffrax.RecursiveCheckpointAdjoint())
    dyn, static = eqx.partition(args, eqx.is_array)
    return _differentiable(static, max_steps)(dyn)


def _closes_over_tracers(scene: Scene, t0) -> bool:
    """Whether the scene's functions close over traced values (a reference written as a
    closure over a traced amplitude, say) rather than holding them as leaves."""
    dyn, static = eqx.partition(scene, eqx.is_array)

    def fields(dyn, t, y):
        sc = eqx.combine(dyn, static)
        return sc.vector_field(t, y), sc.observe(t, y)

    _, consts = jax.closure_convert(fields, dyn, t0, scene.y0)
    return any(isinstance(c, jax.core.Tracer) for c in consts)


_SECOND_ORDER = (
    "second derivatives of an adaptive run through more than "
    "the policy's forward_jacobian_max differentiated scalars need an explicit adjoint: "
    "adjoint=diffrax.DirectAdjoint() (jax.hessian and every other order of forward and "
    "reverse mode) or diffrax.ForwardMode() (forward mode only, e.g. jacfwd of jacfwd)"
)


def _differentiable(static, max_steps: int):
    """The run as a function of its arrays, with the engine's derivatives (module docstring)."""

    def run(dyn, adjoint):
        return _simulate_adaptive(*eqx.combine(dyn, static), max_steps, adjoint)

    @jax.custom_jvp
    def f(dyn):
        return run(dyn, diffrax.RecursiveCheckpointAdjoint())

    def f_jvp(primals, tangents):
        flagged = derivatives.Flagged.of(primals[0], tangents[0])

        def at(adjoint, xs, others=None):  # the run with the differentiated inputs at xs
            return run(flagged.at(xs, others), adjoint)

        if not flagged.xs:
            out = f(*primals)
            return out, derivatives.tangent_tree(
                out, [jnp.zeros_like(y) for y in derivatives.float_leaves(out)]
            )
        if flagged.n <= policy.current().forward_jacobian_max:
            # Differentiated again (second derivatives), the Jacobian program is JAX's
            # jvp of a while loop: forward mode only, so its reverse mode runs by columns.
            forward = lambda xs, others: at(diffrax.ForwardMode(), xs, others)
            return derivatives.ForwardColumns().jvp(forward, flagged)

        # Every input is a residual: JAX may trace the transpose in another trace than
        # this one, so neither function may close over this trace's values.
        def tangent(res, lin):
            forward = lambda *xs: derivatives.float_leaves(at(diffrax.ForwardMode(), xs, res))
            return jax.jvp(forward, tuple(flagged.pick(res)), tuple(lin))[1]

        def transpose(res, cts):
            reverse = lambda *xs: derivatives.float_leaves(
                at(diffrax.RecursiveCheckpointAdjoint(), xs, res)
            )
            return list(jax.vjp(reverse, *flagged.pick(res))[1](cts))

        strategy = derivatives.CustomTranspose(_SECOND_ORDER)
        return strategy.jvp(f(*primals), tangent, transpose, flagged)

    f.defjvp(f_jvp, symbolic_zeros=True)
    return f


@_plan.jit
def _simulate_adaptive(scene, solver, t0, t1, ts, rtol, atol, dt0, max_steps: int, adjoint):
    observe = lambda t, y, args: scene.observe(t, y)
    saveat = diffrax.SaveAt(subs=[diffrax.SubSaveAt(ts=ts, fn=observe), diffrax.SubSaveAt(t1=True)])
    sol = diffrax.diffeqsolve(
        lie_term(scene),
        solver,
        t0,
        t1,
        dt0,
        scene.y0,
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        saveat=saveat,
        max_steps=max_steps,
        adjoint=adjoint,
        throw=False,
    )
    (ts_saved, _), (obs, y_last) = sol.ts, sol.ys
    y = jax.tree.map(lambda a: a[0], y_last)
    rows_ok = jnp.isfinite(ts_saved)  # the points diffrax reached before any failure
    obs = jax.tree.map(
        lambda a: jnp.where(rows_ok.reshape((-1,) + (1,) * (a.ndim - 1)), a, jnp.nan), obs
    )
    i32 = jnp.int32
    n_steps = sol.stats["num_steps"].astype(i32)
    n_acc = sol.stats["num_accepted_steps"].astype(i32)
    status = status_from_diffrax(sol.result, all_finite(y), n_acc)
    # FSAL: one evaluation in `init`, stages - 1 per attempted step, and two for
    # diffrax's initial step selection when dt0 is not given.
    stages = solver.method.tableau.stages
    initial = 0 if dt0 is not None else 2
    stats = {
        "num_steps": n_steps,
        "num_accepted_steps": n_acc,
        "num_rejected_steps": sol.stats["num_rejected_steps"].astype(i32),
        "num_fevals": (stages - 1) * n_steps + 1 + initial,
    }
    return _trajectory(ts, {**obs, **stats}, status, y)
