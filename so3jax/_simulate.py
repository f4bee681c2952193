"""`simulate`: fixed-step integration of a scene under `lax.scan`."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._adaptive import simulate_adaptive
from ._engine import plan as _plan, run
from ._integrators import AbstractLieSolver
from ._scene import Scene, check_rotation, check_vector
from ._so3 import _to_dtype
from ._state import LieState, all_finite
from ._trajectory import (
    NONFINITE,
    NONFINITE_START,
    OK,
    SOLVER_FAILED,
    Status,
    Trajectory,
    _check_dt,
    _check_int,
    _nan_unless,
    _trajectory,
    input_code,
)
from ._types import Array


def simulate(
    scene: Scene,
    method: AbstractLieSolver,
    dt: float | Array | None = None,
    n_steps: int | None = None,
    save_every: int = 1,
    t0: float | Array = 0.0,
    *,
    t1: float | Array | None = None,
    rtol: float | Array | None = None,
    atol: float | Array | None = None,
    saveat: int | Array | None = None,
    max_steps: int = 4096,
    adjoint=None,
    scalarize: bool | None = None,
    compensated: bool = False,
    R0: Array | None = None,
    Omega0: Array | None = None,
) -> Trajectory:
    """Integrate a scene with a fixed-step Lie-group method.

    The steps run under `jax.lax.scan` (compile time does not grow with
    ``n_steps``); every ``save_every``-th state is kept, so memory is
    ``O(n_steps / save_every)``. Works under `jit`, `vmap` (batches of scenes,
    step sizes, gains) and `grad`.

    **Arguments:**

    - `scene`: a scene, e.g. `scenes.free_body(...)`.
    - `method`: a Lie-group method, e.g. `RKMK4()`, `LGVI()`.
    - `dt`: step size (> 0).
    - `n_steps`: number of steps (>= 1), a multiple of ``save_every``.
    - `save_every`: keep one state every this many steps.
    - `t0`: initial time.
    - `scalarize`: leave it at ``None``: the execution engine
      (`so3jax._engine`) runs a single trajectory as the array program and a
      large batch under ``vmap`` (from the engine policy's ``batched_layout``
      threshold, `so3jax._engine.policy.Policy`; ``gpu_layout``'s on a GPU) as the
      scalarized program (every
      scalar component a contiguous batch array, a few fused kernels per step;
      ``benchmarks/throughput.py`` measures it). Through up to
      the engine policy's ``forward_jacobian_max`` differentiated scalars it differentiates a
      run in one pass with its Jacobian's columns; through more, with JAX's ``jvp`` in
      forward mode and the engine's discrete adjoint in reverse mode
      (`so3jax._engine.derivatives`).
      ``True`` / ``False`` force the scalarized /
      array forward program whatever the batching (for benchmarks); a step with
      an operation the scalarizer does not handle (a loop, dynamic indexing)
      runs the array program. Fixed steps only.
    - `compensated`: sum the rotation updates ``R <- R + dR`` with Kahan
      compensation. Without it the rounding of that sum random-walks off the
      group (``||R^T R - I||`` about 1e-13 after 1e6 float64 steps); with it the
      drift stays near 1e-15, for a few percent more time. Fixed steps only.
    - `R0`, `Omega0`: start the body from this attitude `(3, 3)` and/or body rate
      `(3,)` instead of the scene's, as if the scene had been built with them (a
      tracking controller's memory is set for ``R0``). To run a batch of starts,
      ``vmap`` over these rather than over scenes with the start written into
      ``scene.y0``: the scene's reference attitude then stays unbatched, and a
      batch integrates it once instead of once per run
      (``benchmarks/shared_reference.py``).

    **Returns:** a `Trajectory` with ``n_steps // save_every + 1`` points and a
    `Status` saying whether the run stayed finite and where it stopped if not.

    **Adaptive mode:** give ``t1`` and tolerances ``rtol`` / ``atol`` instead of
    ``n_steps`` (with an embedded pair: `RKMK45()`, `RKMKTsit5()`, `RKMK32()`); ``dt`` is
    then the optional initial step, ``saveat`` the saved times (a count or an array)
    and ``max_steps`` the step budget. See `so3jax._adaptive.simulate_adaptive`.
    """
    if t1 is not None or rtol is not None or atol is not None:
        if scalarize is not None or compensated:
            raise ValueError("scalarize and compensated are for fixed steps (dt, n_steps)")
        if n_steps is not None or save_every != 1:
            raise ValueError(
                "adaptive mode (t1, rtol, atol) takes no n_steps or save_every: use saveat"
            )
        if t1 is None:
            raise ValueError("adaptive mode (rtol/atol given) needs the final time t1")
        scene = start_scene(scene, R0, Omega0, apart=False)[0]
        return simulate_adaptive(
            scene,
            method,
            t1,
            rtol,
            atol,
            t0=t0,
            saveat=saveat,
            dt0=dt,
            max_steps=max_steps,
            adjoint=adjoint,
        )
    if dt is None or n_steps is None:
        raise ValueError("pass dt and n_steps (fixed steps), or t1 and rtol/atol (adaptive steps)")
    if saveat is not None:
        raise ValueError("saveat is for adaptive mode (t1, rtol, atol); use save_every")
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a so3jax scene, got {type(scene).__name__}")
    if not isinstance(method, AbstractLieSolver):
        raise TypeError(
            f"method must be a so3jax Lie-group method (e.g. so3jax.RKMK4()), got {method!r}"
        )
    n_steps = _check_int(n_steps, "n_steps", 1)
    save_every = _check_int(save_every, "save_every", 1)
    if n_steps % save_every:
        raise ValueError(f"n_steps ({n_steps}) must be a multiple of save_every ({save_every})")
    scene, R0 = start_scene(scene, R0, Omega0)
    return simulate_from(scene, R0, method, dt, n_steps, save_every, scalarize, t0, compensated)


def start_scene(scene: Scene, R0=None, Omega0=None, apart: bool = True):
    """``(scene, R0)``: ``scene`` set to start from ``(R0, Omega0)`` (``None``: its own).

    The rate goes into ``y0.x[:3]``. What depends on the body's initial attitude
    is recomputed (`Scene.restarted`). Where the scene has time-driven rotation
    groups and no step-dependent setup (`Scene.for_step`), and ``apart`` is set,
    ``R0`` is returned apart for `simulate_from` (a batch of starts then shares
    those groups); otherwise it is written into ``y0.R[0]`` and ``None`` returned.
    """
    if Omega0 is not None:
        Omega0 = check_vector(Omega0, "Omega0").astype(scene.y0.x.dtype)
        scene = eqx.tree_at(lambda s: s.y0.x, scene, scene.y0.x.at[:3].set(Omega0))
    if R0 is None:
        return scene, None
    R0 = check_rotation(R0, "R0").astype(scene.y0.R.dtype)
    scene = scene.restarted(R0)
    if apart and scene.time_driven_groups and type(scene).for_step is Scene.for_step:
        return scene, R0
    return eqx.tree_at(lambda s: s.y0.R, scene, scene.y0.R.at[0].set(R0)), None


def guarded_step(scene, method, dt, t0, compensated: bool = False):
    """The scan body of a fixed-step run: one step, frozen at the last good state.

    The carry is ``(y, k, code, bad)``: state, step index, `Status` code and the
    index of the failed step. A step that is not finite (or whose implicit solve
    failed) sets the code once and leaves ``y`` at its last good value, except
    the scene's `time_driven_groups` (a reference attitude), which run on.

    With ``compensated`` the carry has a fifth entry, the Kahan compensation
    ``c`` of the rotations: ``R <- R + dR`` is summed as ``z = dR - c``,
    ``R1 = R + z``, ``c = (R1 - R) - z``, so the rounding of the sum no longer
    random-walks (about ``sqrt(n) eps`` after ``n`` steps) but stays at ``eps``.
    """

    def one_step(carry, _):
        y, k, code, bad, *comp = carry  # comp: [c] when compensated, else []
        t = t0 + k * dt
        if compensated:
            (c,) = comp
            dR, x1, failed = method.increment(scene, t, y, dt)
            z = dR - c
            R1 = y.R + z
            c1 = (R1 - y.R) - z
            y1 = LieState(R1, x1)
        else:
            y1, failed = method.step(scene, t, y, dt)
        y1 = scene.jump(t + dt, y1)
        finite = all_finite(y1)
        newly = (code == OK) & (failed | ~finite)
        code = jnp.where(newly, jnp.where(finite, SOLVER_FAILED, NONFINITE), code)
        bad = jnp.where(newly, k, bad)
        keep = code == OK
        y = LieState(freeze(keep, y1.R, y.R), jnp.where(keep, y1.x, y.x))
        if compensated:
            comp = [freeze(keep, c1, c)]
        return (y, k + 1, code, bad, *comp), None

    shared = tuple(scene.time_driven_groups)

    def freeze(keep, new, old):
        """``new`` while the run is good, ``old`` after; time-driven groups always ``new``.

        Selecting those on ``keep`` would make them differ between the runs of a
        batch; left alone, runs that share a start share them (one computation
        in the scalarized batch program).
        """
        if not shared:
            return jnp.where(keep, new, old)
        groups = [
            new[g] if g in shared else jnp.where(keep, new[g], old[g]) for g in range(new.shape[0])
        ]
        return jnp.stack(groups)

    return one_step


def _program(scalarize) -> str:
    """The engine's program for the ``scalarize`` override (``None``: the engine decides)."""
    if scalarize is None:
        return "auto"
    return "scalar" if scalarize else "array"


def split_scene(scene, method, dt, t0):
    """``(params, unpack)``: the arrays of a run, and how to rebuild its pieces.

    ``params`` holds every array of the scene and the method with ``dt`` and
    ``t0`` (what the engine differentiates and batches); ``unpack(params)``
    returns ``(scene, method, dt, t0)``.
    """
    dyn, static = eqx.partition((scene, method), eqx.is_array)

    def unpack(P):
        sc, m = eqx.combine(P[0], static)
        return sc, m, P[1], P[2]

    return (dyn, dt, t0), unpack


def simulate_from(
    scene,
    R0,
    method,
    dt,
    n_steps: int,
    save_every: int = 1,
    scalarize=None,
    t0=0.0,
    compensated: bool = False,
):
    """A fixed-step `simulate` (arguments already checked) with the body's start
    ``R0`` given apart (``None``: the scene's own).

    For batches of starts (`sweep`): the scene's own attitude array, with its
    reference ``Rd0``, stays unbatched, and so does ``Rd`` (see `split_groups`).
    """
    dtype = scene.y0.R.dtype
    dt = _check_dt(dt, dtype)
    t0 = _to_dtype(t0, dtype)
    scene = scene.for_step(dt, t0)
    n_save = n_steps // save_every
    program = _program(scalarize)
    return _simulate(scene, method, dt, t0, n_save, save_every, program, bool(compensated), R0)


def split_groups(y: LieState, R0=None) -> tuple:
    """``(groups, x)``: the state with each rotation group its own array.

    The engine batches and scalarizes per array: with the groups apart, a
    batch whose runs share a time-driven group (a reference attitude) keeps
    that group unbatched. ``R0`` replaces group 0 (a batched start next to
    shared groups: stacking it into ``y.R`` first would batch them all).
    """
    groups = [y.R[g] for g in range(y.R.shape[0])]
    if R0 is not None:
        groups[0] = jnp.asarray(R0, y.R.dtype)
    return tuple(groups), y.x


def join_groups(groups, x) -> LieState:
    return LieState(jnp.stack(groups), x)


def engine_step(guarded):
    """A `guarded_step` body over carries whose state is split into groups."""

    def step(carry):
        (groups, x), *rest = carry
        (y1, *rest1), _ = guarded((join_groups(groups, x), *rest), None)
        return (split_groups(y1), *rest1)

    return step


@_plan.jit
def _simulate(
    scene,
    method,
    dt,
    t0,
    n_save: int,
    save_every: int,
    program: str = "auto",
    compensated: bool = False,
    R0=None,
) -> Trajectory:
    y0 = scene.y0
    params, unpack = split_scene(scene, method, dt, t0)

    def step(P, carry):
        sc, m, dt, t0 = unpack(P)
        return engine_step(guarded_step(sc, m, dt, t0, compensated))(carry)

    def observe(P, carry):
        sc, _, dt, t0 = unpack(P)
        (groups, x), k = carry[:2]
        return sc.observe(t0 + k * dt, join_groups(groups, x))

    start = split_groups(y0, R0)
    y0 = join_groups(*start)
    i32 = jnp.int32
    code0 = input_code(scene, dt, *start)
    init = (start, jnp.array(0, i32), code0, jnp.array(-1, i32))
    if compensated:
        init = init + (jnp.zeros_like(y0.R),)
    obs, ((groups, x), _, code, bad, *_) = run(
        step, observe, params, init, n_save * save_every, save_every, program=program
    )
    y = join_groups(groups, x)
    code = diagnose(scene, code, t0 + jnp.maximum(bad, 0) * dt, y)
    started = code0 == OK
    obs0 = _nan_unless(started, scene.observe(t0, y0))
    y = _nan_unless(started, y)
    # The saved times are the step counter's, ``t0 + k dt`` as the step has them. Computed
    # here, not saved by the loop, they stay unbatched where ``t0`` and ``dt`` are (a
    # sweep's runs): a cost on the trajectory evaluates the reference once per time.
    k = save_every * jnp.arange(n_save + 1, dtype=i32)
    t = t0 + k * dt
    # A point saved after the step that failed (index `bad`) is NaN. Masked here, not in
    # the loop, the observations that are the same for every run of a batch (the
    # reference attitude of a sweep) stay so in the loop: saved once, not once per run.
    good = (code == OK) | (k[1:] <= bad)
    obs = jax.tree.map(
        lambda a0, a: jnp.concatenate(
            [a0[None], jnp.where(good.reshape((-1,) + (1,) * (a.ndim - 1)), a, jnp.nan)]
        ),
        obs0,
        obs,
    )
    t_bad = jnp.where(bad >= 0, t0 + bad * dt, jnp.nan)
    return _trajectory(t, obs, Status(code=code, step=bad, t=t_bad), y)


def diagnose(scene, code: Array, t: Array, y: LieState) -> Array:
    """``code``, with "not finite" replaced by the cause `Scene.fault` names at ``(t, y)``.

    ``y`` is the last good state (the start, for a run whose input was not finite).
    Evaluated once per run, after the loop: the loop itself is unchanged.
    """
    if type(scene).fault is Scene.fault:
        return code
    cause = scene.fault(t, y)
    return jnp.where(((code == NONFINITE) | (code == NONFINITE_START)) & (cause != OK), cause, code)
