"""Tracking cost and gradient-based tuning of the geometric controller's gains.

The cost of a tracking run is a time integral of the attitude error, the
angular-velocity error and the control effort,

    C = int_0^T ( w_Psi Psi + w_Omega |e_Omega|^2 + w_M |M|^2 ) dt,

so that the best gains are finite: small gains track slowly (``Psi`` stays
large), large gains pay in torque. `tracking_cost` evaluates it on a saved
`Trajectory` (trapezoid over the saved points); `rollout_cost` integrates it
alongside the simulation without saving anything and differentiates in memory
sublinear in the horizon (a checkpointed scan of blocks of steps); `tune`
minimises its mean over a batch of initial attitudes with optax.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import os
import warnings
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._control import GeometricController, GeometricGains, _check_gain
from ._engine import derivatives, plan as _plan, run
from ._engine.passes.frames import Frame, frame_rule, right_or_zero
from ._engine.policy import current, using
from ._integrators import RKMK4, AbstractLieSolver
from ._scene import Scene, check_rotation
from ._simulate import (
    engine_step,
    guarded_step,
    input_code,
    join_groups,
    split_groups,
    split_scene,
)
from ._so3 import _FULL, _as_float, _cross, _is_concrete, _mm, _mT, _mtv, _mv, _vee
from ._trajectory import OK, Trajectory, _check_dt, _check_int
from ._types import Array, ArrayLike

# --------------------------------------------------------------------------
# Scenes with other gains and initial states
# --------------------------------------------------------------------------


def own_compiler_options() -> dict | None:
    """The active policy's compiler options for the default backend, less what
    ``XLA_FLAGS`` sets; or ``None``."""
    flags = os.environ.get("XLA_FLAGS", "")
    options = current().compiler_options(jax.default_backend())
    options = {k: v for k, v in options.items() if f"--{k}=" not in flags}
    return options or None


def jit_own(fn: Callable) -> Callable:
    """``jax.jit(fn)`` for a program the library compiles itself, with `own_compiler_options`.

    Should XLA not know an option (a later jaxlib may drop one), the program compiles with
    XLA's defaults instead, with a warning.
    """
    plain = jax.jit(fn)
    options = own_compiler_options()
    if options is None:
        return plain
    try:
        tuned = jax.jit(fn, compiler_options=options)
    except TypeError:  # pragma: no cover - a JAX whose `jit` takes no compiler options
        return plain
    rejected = []

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if not rejected:
            try:
                return tuned(*args, **kwargs)
            except Exception as e:  # XLA's error type moves between JAX versions
                if "compile option" not in str(e):
                    raise
                rejected.append(e)
                warnings.warn(
                    f"so3jax: XLA rejected the compile options {options} ({e}); "
                    "compiling with its defaults",
                    stacklevel=2,
                )
        return plain(*args, **kwargs)

    return call


def _check_tracking_scene(scene, name: str = "scene") -> None:
    """A tracking scene driven by the geometric controller (what sweeps and tuning vary)."""
    if not isinstance(scene, Scene):
        raise TypeError(f"{name} must be a so3jax scene, got {type(scene).__name__}")
    controller = getattr(scene, "controller", None)
    if not isinstance(controller, GeometricController) or not hasattr(scene, "reference"):
        raise ValueError(
            f"{name} must be a tracking scene with the geometric controller, e.g. "
            "so3jax.scenes.seed() or so3jax.scenes.tracking(inertia, GeometricGains(...), ...); "
            f"got {type(scene).__name__} with controller {type(controller).__name__}"
        )


def with_gains(scene, k_R: Array, k_Omega: Array):
    """The scene with the geometric gains replaced (traceable: works under `vmap`/`grad`).

    Each gain is checked as `GeometricGains` checks it (shape `()` or `(3,)`, and,
    when concrete, finite and non-negative): a `ValueError` naming it otherwise.
    """
    dtype = scene.y0.R.dtype
    k_R, k_Omega = _check_gain(k_R, "k_R"), _check_gain(k_Omega, "k_Omega")
    return eqx.tree_at(
        lambda s: (s.controller.gains.k_R, s.controller.gains.k_Omega),
        scene,
        (k_R.astype(dtype), k_Omega.astype(dtype)),
    )


def with_initial_state(scene, R0: Array, Omega0: Array):
    """The scene started from ``(R0, Omega0)`` (the reference ``Rd0`` is kept)."""
    scene, R0 = with_start(scene, R0, Omega0)
    return eqx.tree_at(lambda s: s.y0.R, scene, jnp.stack([R0, scene.y0.R[1]]))


def with_start(scene, R0: Array, Omega0: Array):
    """``(scene, R0)``: the scene's rates and controller memory set for a start at
    ``(R0, Omega0)``, its attitude array left alone; run it with ``R0`` apart
    (`split_groups`), so a batch of starts shares the reference ``Rd``."""
    dtype = scene.y0.R.dtype
    R0 = jnp.asarray(R0, dtype)
    x = scene.y0.x.at[:3].set(jnp.asarray(Omega0, dtype))
    return eqx.tree_at(lambda s: s.y0.x, scene, x).restarted(R0), R0


def _gain_array(value, name: str, dtype) -> Array:
    k = _check_gain(value, name)
    if _is_concrete(k) and not (np.all(np.isfinite(np.asarray(k))) and np.all(np.asarray(k) > 0)):
        raise ValueError(f"{name} must be positive and finite, got {np.asarray(k)}")
    return k.astype(dtype)


# --------------------------------------------------------------------------
# The cost
# --------------------------------------------------------------------------


class CostWeights(eqx.Module):
    """Weights of the tracking cost ``w_Psi Psi + w_Omega |e_Omega|^2 + w_M |M|^2``.

    The default makes the optimum of the seed scenario finite and close to
    the published gains: effort is cheap, but not free.

    **Arguments:**

    - `psi`: weight ``w_Psi`` of the attitude error function ``Psi`` (>= 0).
    - `omega`: weight ``w_Omega`` of ``|e_Omega|^2`` in (rad/s)^-2 (>= 0).
    - `effort`: weight ``w_M`` of ``|M|^2`` in (N m)^-2 (> 0 keeps the
      optimal gains finite).
    """

    psi: Array
    omega: Array
    effort: Array

    def __init__(self, psi: ArrayLike = 1.0, omega: ArrayLike = 0.1, effort: ArrayLike = 0.01):
        for value, name in ((psi, "psi"), (omega, "omega"), (effort, "effort")):
            v = _as_float(value)
            if v.shape != ():
                raise ValueError(f"CostWeights.{name} must be a scalar, got shape {v.shape}")
            if _is_concrete(v) and not (math.isfinite(float(v)) and float(v) >= 0):
                raise ValueError(f"CostWeights.{name} must be >= 0 and finite, got {float(v)}")
        self.psi = _as_float(psi)
        self.omega = _as_float(omega)
        self.effort = _as_float(effort)


def _integrand(weights: CostWeights, R, Omega, Rd, M, Omega_d) -> Array:
    """``w_Psi Psi + w_Omega |e_Omega|^2 + w_M |M|^2`` at one or many points."""
    return _integrand_of(weights.psi, weights.omega, weights.effort, R, Omega, Rd, M, Omega_d)


def _integrand_raw(w_psi, w_omega, w_effort, R, Omega, Rd, M, Omega_d):
    psi, _, e_Omega = _integrand_errors(R, Omega, Rd, Omega_d)
    return _weighted(w_psi, w_omega, w_effort, psi, e_Omega, M)


def _sum3(x):
    """``x`` summed over its last axis of three, as two additions.

    On arrays of saved points (a cost on a trajectory), XLA's CPU compiler hands
    ``jnp.sum`` over an axis of three, with everything that feeds it, to a library
    reduction (YNNPACK), several times slower than the same sums as additions in one
    elementwise loop, in the forward pass, its ``jvp`` and its gradient alike. In the
    scalarized loops both are the same additions.
    """
    a, b, c = jnp.split(x, 3, axis=-1)  # (its transpose is one concatenation, where
    return (a + b + c)[..., 0]  # three slices would transpose to three pads)


def _dot3(x, y):
    """``sum(x * y, -1)`` over a last axis of three, as a sum of its components' products.

    `_sum3` of ``x * y`` reads each product three times, so XLA's CPU compiler stores the
    products first: an array the size of the saved attitudes. Summed products are one
    elementwise loop, and needs less temp memory (a cost on saved runs, forward pass and
    gradient alike)."""
    x0, x1, x2 = jnp.split(x, 3, axis=-1)
    y0, y1, y2 = jnp.split(y, 3, axis=-1)
    return (x0 * y0 + x1 * y1 + x2 * y2)[..., 0]


def _integrand_errors(R, Omega, Rd, Omega_d):
    """``(Psi, a, e_Omega)`` with ``a = R^T Rd Omega_d``."""
    psi = 0.5 * (3.0 - _sum3(_dot3(Rd, R)))
    # e_Omega = Omega - R^T Rd Omega_d (Lee, Leok & McClamroch 2010, eq. (11)).
    b = _dot3(Rd, Omega_d[..., None, :])  # Rd Omega_d
    a = _dot3(jnp.swapaxes(R, -1, -2), b[..., None, :])  # R^T b
    return psi, a, Omega - a


def _weighted(w_psi, w_omega, w_effort, psi, e_Omega, M):
    return w_psi * psi + w_omega * _dot3(e_Omega, e_Omega) + w_effort * _dot3(M, M)


@jax.custom_jvp
def _integrand_of(*args):
    """`_integrand_raw` with JAX's own derivative, and a `Frame` rule (below)."""
    return _integrand_raw(*args)


@functools.partial(_integrand_of.defjvp, symbolic_zeros=True)
def _integrand_of_jvp(primals, tangents):
    return derivatives.jvp_through(_integrand_raw, derivatives.Flagged.of(primals, tangents))


@frame_rule(_integrand_of)
def _integrand_frame(xs, ts):
    """The integrand with ``dR = R hat(xi)`` (`so3jax._engine.passes.frames`), and
    ``dRd = Rd hat(zeta)``
    if the reference moves too: ``dPsi = (xi - zeta) . vee(Rd^T R)`` and ``d e_Omega =
    dOmega + xi x a - R^T Rd (zeta x Omega_d + dOmega_d)``, ``a = R^T Rd Omega_d``: 14
    operations a column where the dense tangent takes about 60 (``R hat(xi)``, then both
    products)."""
    w_psi, w_omega, w_effort, R, Omega, Rd, M, Omega_d = xs
    tR, tRd = ts[3], ts[5]
    if tR is None or not (right_or_zero(tR) and right_or_zero(tRd)):
        return None
    if any(isinstance(t, Frame) for i, t in enumerate(ts) if i not in (3, 5)):
        return None
    psi, a, e_Omega = _integrand_errors(R, Omega, Rd, Omega_d)
    value = _weighted(w_psi, w_omega, w_effort, psi, e_Omega, M)
    vee = _vee(_mm(_mT(Rd), R))
    xi = tR.xi if tRd is None else tR.xi - tRd.xi
    d_e = [_cross(tR.xi, a)]
    if ts[4] is not None:
        d_e.append(ts[4])
    ref = []  # R^T Rd times the reference's rate tangents
    if tRd is not None:
        ref.append(_cross(tRd.xi, Omega_d))
    if ts[7] is not None:
        ref.append(ts[7])
    if ref:
        d_e.append(-_mtv(R, _mv(Rd, functools.reduce(jnp.add, ref))))
    d_e = functools.reduce(jnp.add, d_e)
    parts = [w_psi * jnp.sum(xi * vee, -1), 2.0 * w_omega * jnp.sum(e_Omega * d_e, -1)]
    if ts[6] is not None:
        parts.append(2.0 * w_effort * jnp.sum(M * ts[6], -1))
    for w, part in zip(ts[:3], (psi, jnp.sum(e_Omega**2, -1), jnp.sum(M**2, -1)), strict=True):
        if w is not None:
            parts.append(w * part)
    d = functools.reduce(jnp.add, parts)
    return [value], [jnp.broadcast_to(d, value.shape).astype(value.dtype)]


def _desired_rate(reference, t: Array) -> Array:
    """``Omega_d(t)`` for times of any shape (the reference is called on scalars)."""
    flat = jax.vmap(lambda s: reference(s)[0])(t.reshape(-1))
    return flat.reshape(t.shape + (3,))


def _check_weights(weights) -> CostWeights:
    if weights is None:
        return CostWeights()
    if not isinstance(weights, CostWeights):
        raise TypeError(f"weights must be a CostWeights, got {type(weights).__name__}")
    return weights


def tracking_cost(traj: Trajectory, scene, weights: CostWeights | None = None) -> Array:
    """Integrated tracking cost of a saved run (trapezoid rule over the saved points).

    ``C = int ( w_Psi Psi(R, Rd) + w_Omega |e_Omega|^2 + w_M |M|^2 ) dt`` with
    ``e_Omega = Omega - R^T Rd Omega_d(t)``. Differentiable in everything the
    trajectory depends on (gains, inertia, initial state): build the scene
    inside the differentiated function, e.g.
    ``jax.grad(lambda k: tracking_cost(simulate(make(k), ...), make(k)))``.
    A run that stopped being finite has a NaN cost.

    **Arguments:**

    - `traj`: a `Trajectory` of a tracking scene (with ``Rd`` and ``M``), from
      `simulate` or `simulate_ambient`; leading batch axes are allowed.
    - `scene`: the tracking scene it was run from (its reference gives
      ``Omega_d`` at the saved times).
    - `weights`: a `CostWeights` (default `CostWeights()`).

    **Returns:** the cost, shape `()` (or the batch shape of `traj`).

    References: T. Lee, M. Leok, N. H. McClamroch, "Geometric tracking control
    of a quadrotor UAV on SE(3)", CDC 2010 (errors ``Psi``, ``e_Omega``).
    """
    if not isinstance(traj, Trajectory):
        raise TypeError(f"traj must be a Trajectory, got {type(traj).__name__}")
    if traj.Rd is None or traj.M is None:
        raise ValueError(
            "traj must come from a tracking scene (it needs Rd and M), e.g. so3jax.scenes.seed()"
        )
    reference = getattr(scene, "reference", None)
    if not callable(reference):
        raise ValueError(
            "scene must be the tracking scene the trajectory was run from (it needs a reference)"
        )
    weights = _check_weights(weights)
    return _tracking_cost(traj, reference, weights)


def _tracking_cost(traj: Trajectory, reference, weights, chunk_invariant: bool = False):
    """`tracking_cost` after its checks (``chunk_invariant``: `_trapezoid`'s)."""
    Omega_d = _desired_rate(reference, traj.t)
    f = _integrand(weights, traj.R, traj.Omega, traj.Rd, traj.M, Omega_d)
    return _trapezoid(f, traj.t, chunk_invariant)


def _trapezoid(f, t, chunk_invariant: bool = False):
    """``int f dt`` over the last axis by the trapezoid rule, as a product with the
    rule's weights: XLA compiles a ``dot`` where a sum of ``f``'s neighbours became one
    library reduction with everything that computes ``f`` (`_sum3`), which is slower.

    A ``dot`` of a batch (``vmap`` of a run's cost) rounds differently for different
    batch sizes; ``chunk_invariant`` sums the products instead, the same in every chunk
    (`so3jax.sweep` gives chunked and whole sweeps bit for bit the same costs)."""
    dt = jnp.diff(t, axis=-1)
    zero = jnp.zeros_like(dt[..., :1])
    w = 0.5 * (jnp.concatenate([dt, zero], -1) + jnp.concatenate([zero, dt], -1))
    if chunk_invariant:
        return jnp.sum(f * w, axis=-1)
    return jnp.einsum("...n,...n->...", f, w, precision=_FULL)


def _point_cost(scene, weights, t, y) -> Array:
    obs = scene.observe(t, y)
    Omega_d = scene.reference(t)[0]
    return _integrand(weights, obs["R"], obs["Omega"], obs["Rd"], obs["M"], Omega_d)


def _block_size(checkpoint_every, n_save: int, save_every: int) -> int | None:
    """Saved intervals per checkpointed block (``None``: no checkpointing)."""
    if checkpoint_every is None:
        return None
    if checkpoint_every == "auto":
        return max(1, round(math.sqrt(n_save)))
    steps = _check_int(checkpoint_every, "checkpoint_every", 1)
    return max(1, min(n_save, steps // save_every))


def rollout_cost(
    scene,
    method: AbstractLieSolver,
    dt: float | Array,
    n_steps: int,
    weights: CostWeights | None = None,
    *,
    save_every: int = 1,
    checkpoint_every: int | str | None = "auto",
    t0: float | Array = 0.0,
    program: str = "auto",
) -> Array:
    """The tracking cost of a run without its trajectory, with checkpointed gradients.

    Equal to ``tracking_cost(simulate(scene, method, dt, n_steps, save_every),
    scene, weights)`` (the trapezoid over every ``save_every``-th step), but
    no trajectory is kept: with ``save_every=1`` the integral is summed as the
    run goes (nothing is saved per step, in the run or its derivatives); with
    a larger ``save_every`` the integrand is saved at its points (one scalar
    each). Reverse mode
    keeps one state per block of ``checkpoint_every`` steps and recomputes
    each block (`jax.checkpoint` around an inner `lax.scan`), so the memory of
    a gradient grows like ``n / B + B`` steps (``sqrt(n)`` for the default),
    not like ``n``. A run that stops being finite has a NaN cost.

    **Arguments:**

    - `scene`: a tracking scene (with ``Rd``, ``M`` observed and a reference).
    - `method`: a Lie-group method, e.g. `RKMK4()`.
    - `dt`: step size (> 0).
    - `n_steps`: number of steps, a multiple of `save_every`.
    - `weights`: a `CostWeights` (default `CostWeights()`).
    - `save_every`: integrate the cost over every this many steps.
    - `checkpoint_every`: steps per checkpointed block; ``"auto"`` (about
      ``sqrt(n_steps)``) or ``None`` (no checkpointing: memory linear in the
      horizon).
    - `t0`: initial time.
    - `program`: how the engine runs it (`so3jax._engine.run`); leave it at
      ``"auto"`` except to compare programs in benchmarks.

    **Returns:** the cost, shape `()`.

    References: A. Griewank, A. Walther, "Evaluating Derivatives", SIAM 2008,
    ch. 12 (checkpointing).
    """
    args = _rollout_args(scene, method, dt, n_steps, weights, save_every, checkpoint_every, t0)
    return _rollout(scene.for_step(args[1], args[2]), *args, program)


def _rollout_args(scene, method, dt, n_steps, weights, save_every, checkpoint_every, t0):
    """Checked arguments of `_rollout` after the scene: ``(method, dt, t0, weights,
    n_save, save_every, block)``."""
    if not isinstance(scene, Scene) or not callable(getattr(scene, "reference", None)):
        raise ValueError(f"scene must be a tracking scene, got {type(scene).__name__}")
    if not isinstance(method, AbstractLieSolver):
        raise TypeError(f"method must be a so3jax Lie-group method, got {method!r}")
    weights = _check_weights(weights)
    n_steps = _check_int(n_steps, "n_steps", 1)
    save_every = _check_int(save_every, "save_every", 1)
    if n_steps % save_every:
        raise ValueError(f"n_steps ({n_steps}) must be a multiple of save_every ({save_every})")
    if checkpoint_every is not None and checkpoint_every != "auto":
        _check_int(checkpoint_every, "checkpoint_every", 1)
    dtype = scene.y0.R.dtype
    dt = _check_dt(dt, dtype)
    t0 = jnp.asarray(t0, dtype)
    n_save = n_steps // save_every
    block = _block_size(checkpoint_every, n_save, save_every)
    return method, dt, t0, weights, n_save, save_every, block


@_plan.jit
def _rollout(
    scene, method, dt, t0, weights, n_save: int, save_every: int, block, program="auto", R0=None
):
    # The step logic is that of `simulate` (freeze on failure), so the costs agree;
    # the engine runs it (array / scalarized / discrete adjoint, see `so3jax._engine`).
    # ``R0`` replaces the body's start (see `split_groups`).
    params, unpack = split_scene(scene, method, dt, t0)
    n_steps = n_save * save_every

    def step(P, state):
        sc, m, dt, t0 = unpack(P[0])
        return engine_step(guarded_step(sc, m, dt, t0))(state)

    def integrand(P, state):  # the cost's integrand at a state (NaN once the run failed)
        sc, _, dt, t0 = unpack(P[0])
        (groups, x), k, code, _ = state
        y = join_groups(groups, x)
        return jnp.where(code == OK, _point_cost(sc, P[1], t0 + k * dt, y), jnp.nan)

    start = split_groups(scene.y0, R0)
    y0 = join_groups(*start)
    # Input that is bad under a trace (a traced dt <= 0, a start off the group): the
    # run never starts and its cost is NaN, as `simulate`'s status would say.
    code0 = input_code(scene, dt, *start)
    f0 = jnp.where(code0 == OK, _point_cost(scene, weights, t0, y0), jnp.nan)
    i32 = jnp.int32
    state = (start, jnp.array(0, i32), code0, jnp.array(-1, i32))
    checkpoint = n_steps if block is None else block * save_every
    P = (params, weights)
    if save_every > 1:  # the integrand at every save_every-th step, saved
        fs, _ = run(
            step, integrand, P, state, n_steps, save_every, checkpoint=checkpoint, program=program
        )
        f = jnp.concatenate([f0[None], fs])
        return jnp.sum(0.5 * (f[1:] + f[:-1])) * (dt * save_every)

    # Every step is a point: the integral is summed in the carry and nothing is
    # saved. A derivative then stores no column per step, and its memory does not
    # grow with the horizon (it is faster too than saving the points: docs/engine.md).
    # The carry holds the last point's integrand and adds each trapezoid whole, so the
    # cost is linear in the final carry: a second derivative (``jax.hessian``) then needs
    # no value of the Jacobian program beside its ``jvp`` (one loop, not two).
    def step_and_sum(P, carry):
        state, total, f = carry
        state = step(P, state)
        f1 = integrand(P, state)
        return state, total + 0.5 * (f + f1), f1

    # (the first trapezoid's f0 is added outside: a start with no tangent in the carry)
    zero = jnp.zeros((), f0.dtype)
    _, (_, total, _) = run(
        step_and_sum,
        lambda P, c: (),
        P,
        (state, zero, zero),
        n_steps,
        checkpoint=checkpoint,
        program=program,
    )
    return (total + 0.5 * f0) * dt


# --------------------------------------------------------------------------
# Tuning
# --------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TuneResult:
    """What `tune` found.

    **Fields:**

    - `gains`: the `GeometricGains` with the lowest cost seen.
    - `cost`: its (batch-mean) cost.
    - `initial_cost`: the cost of the initial gains.
    - `cost_history`: the cost at every iterate, shape `(n_iter + 1,)`.
    - `k_R_history`, `k_Omega_history`: the gains at every iterate, shape
      `(n_iter + 1,)` or `(n_iter + 1, 3)` (per-axis gains).
    - `best_iteration`: index of `gains` in the histories.
    - `gains_history`: with a custom ``cost``, the gains at every iterate, a
      pytree like `gains` whose leaves have a leading axis of length
      ``n_iter + 1`` (``None`` for the default tracking cost, whose histories
      are `k_R_history` and `k_Omega_history`).
    - `gradient`: the mode each iteration's gradient was taken in, ``"forward"`` or
      ``"reverse"`` (what ``gradient="auto"`` chose for the number of tuned scalars).

    With a custom ``cost`` (`tune`'s general mode), `gains` is a pytree like
    ``gains0`` and `k_R_history`, `k_Omega_history` are filled only when the
    gains have ``k_R`` and ``k_Omega`` fields (``None`` otherwise).
    """

    gains: object
    cost: float
    initial_cost: float
    cost_history: np.ndarray
    k_R_history: np.ndarray | None
    k_Omega_history: np.ndarray | None
    best_iteration: int
    gains_history: object = None
    gradient: str | None = None


def _check_batch_shape(x, name: str, trailing: tuple[int, ...]) -> None:
    """``x`` must have shape ``(B, *trailing)``: a `ValueError` naming it otherwise."""
    shape = tuple(jnp.shape(x))
    if len(shape) != 1 + len(trailing) or shape[1:] != trailing:
        want = "(B, " + ", ".join(map(str, trailing)) + ")"
        raise ValueError(f"{name} must have shape {want} (a batch of starts), got {shape}")


def _initial_batch(scene, R0, Omega0):
    dtype = scene.y0.R.dtype
    if R0 is None:
        R0 = scene.y0.R[0][None]
    R0 = jnp.asarray(R0, dtype)
    if R0.ndim == 2:
        R0 = R0[None]
    if R0.ndim != 3 or R0.shape[1:] != (3, 3):
        raise ValueError(f"R0 must have shape (3, 3) or (batch, 3, 3), got {R0.shape}")
    if Omega0 is None:
        Omega0 = jnp.broadcast_to(scene.y0.x[:3], (R0.shape[0], 3))
    Omega0 = jnp.asarray(Omega0, dtype)
    if Omega0.ndim == 1:
        Omega0 = jnp.broadcast_to(Omega0, (R0.shape[0], 3))
    if Omega0.shape != (R0.shape[0], 3):
        raise ValueError(f"Omega0 must have shape (3,) or ({R0.shape[0]}, 3), got {Omega0.shape}")
    return R0, Omega0


def expected_cost(
    scene,
    k_R: Array,
    k_Omega: Array,
    R0: Array,
    Omega0: Array,
    method: AbstractLieSolver,
    dt,
    n_steps: int,
    weights: CostWeights | None = None,
    *,
    save_every: int = 1,
    checkpoint_every: int | str | None = "auto",
    program: str = "auto",
) -> Array:
    """Mean `rollout_cost` over a batch of initial states, for given gains.

    ``C(k) = 1/B sum_b C(k; R0_b, Omega0_b)``, vmapped over the batch.

    **Arguments:**

    - `scene`: a tracking scene with the geometric controller.
    - `k_R`, `k_Omega`: gains, shape `()` or `(3,)`.
    - `R0`: initial attitudes, shape `(B, 3, 3)`.
    - `Omega0`: initial rates, shape `(B, 3)`.
    - `method`, `dt`, `n_steps`, `weights`, `save_every`, `checkpoint_every`,
      `program`: as in `rollout_cost`.

    **Returns:** the mean cost, shape `()`.
    """

    args = _rollout_args(scene, method, dt, n_steps, weights, save_every, checkpoint_every, 0.0)
    _check_batch_shape(R0, "R0", (3, 3))
    _check_batch_shape(Omega0, "Omega0", (3,))
    if R0.shape[0] != Omega0.shape[0]:
        raise ValueError(
            f"R0 and Omega0 must hold the same number of starts, got {R0.shape[0]} and "
            f"{Omega0.shape[0]}"
        )

    def one(R, W):
        # The start goes in apart from the scene's attitudes, so the batch shares Rd.
        sc, R = with_start(with_gains(scene, k_R, k_Omega), R, W)
        return _rollout(sc.for_step(args[1], args[2]), *args, program, R0=R)

    return jnp.mean(jax.vmap(one)(R0, Omega0))


def tune(
    scene,
    gains0=None,
    *,
    method: AbstractLieSolver | None = None,
    dt: float = 1e-2,
    n_steps: int = 300,
    save_every: int = 1,
    R0: Array | None = None,
    Omega0: Array | None = None,
    weights: CostWeights | None = None,
    n_iter: int = 100,
    learning_rate: float = 0.1,
    optimizer=None,
    per_axis: bool = False,
    checkpoint_every: int | str | None = "auto",
    gradient: str = "auto",
    progress: bool = False,
    cost: Callable | None = None,
    bounds: tuple | None = None,
    where: Callable | None = None,
    starts=None,
) -> TuneResult:
    """Tune a controller's gains by gradient descent on a cost of the trajectory.

    Minimises ``C(k) = 1/B sum_b C(k; R0_b)`` (`expected_cost`) over
    ``k = (k_R, k_Omega)`` in log coordinates ``k = exp(theta)`` (the gains
    stay positive) with optax (Adam by default). Each iteration is one jitted
    value-and-gradient through the checkpointed rollout (`rollout_cost`);
    an iterate whose cost or gradient is not finite is skipped
    (`optax.apply_if_finite`).

    **Arguments:**

    - `scene`: a tracking scene with the geometric controller (e.g. `scenes.seed()`).
    - `gains0`: initial gains, a `GeometricGains` or ``(k_R, k_Omega)`` (> 0).
    - `method`: a Lie-group method (default `RKMK4()`).
    - `dt`, `n_steps`, `save_every`: the horizon ``n_steps * dt``.
    - `R0`: initial attitudes averaged over, shape `(B, 3, 3)` (default: the
      scene's own initial attitude), e.g. `random_rotation(key, (B,))`.
    - `Omega0`: initial rates, shape `(3,)` or `(B, 3)` (default: the scene's).
    - `starts`: the initial states in one argument, instead of `R0` / `Omega0`:
      attitudes `(B, 3, 3)`, or a pair ``(R0, Omega0)``.
    - `weights`: a `CostWeights`.
    - `n_iter`: number of optimiser steps.
    - `learning_rate`: Adam's step in log-gain (0.1: about 10% per step).
    - `optimizer`: an optax `GradientTransformation` (overrides the two above).
    - `per_axis`: tune 3-vectors of gains (one per body axis) instead of scalars.
    - `checkpoint_every`: as in `rollout_cost`.
    - `gradient`: ``"auto"`` (default: forward mode through at most
      `FORWARD_MODE_MAX` (8) tuned scalars, reverse mode beyond), ``"reverse"``
      (`jax.grad`) or ``"forward"`` (`jax.jacfwd`, one tangent per scalar,
      constant memory). With 2 or 6 gains both run the engine's one-pass
      Jacobian at about the same cost; through a dozen gains of one run
      (DiffTune's 12 quadrotor gains) reverse mode, the engine's discrete adjoint,
      runs several times faster (``benchmarks/difftune.py``). With one start its
      forward pass keeps every step's residuals for the backward pass (within the
      engine policy's ``tune_residual_bytes``; memory linear in `n_steps`), with a
      batch of starts checkpointed segments (``benchmarks/adjoint.py``).
    - `progress`: show a tqdm progress bar.

    **General mode** (``cost`` given): any scene, any pytree of gains, any
    differentiable cost. Minimises ``cost(simulate(scene with gains, method,
    dt, n_steps, save_every))`` over the gains themselves (no log
    coordinates), with optional box constraints by projection (DiffTune's
    ``gains >= 0.5`` is ``bounds=(0.5, None)``):

    - `cost`: a function ``Trajectory -> scalar``, differentiable, e.g.
      ``lambda tr: jnp.sum(tr.extras["e_x"] ** 2)``.
    - `gains0`: the initial gains, a pytree like ``where(scene)`` (default:
      the scene's own gains).
    - `where`: a function ``scene -> gains`` naming what is tuned (default:
      ``scene.gains`` if the scene has it, else ``scene.controller.gains``).
    - `bounds`: ``(lower, upper)``, each ``None``, a scalar or a pytree like
      the gains; after every update the gains are clipped to them.
    - `optimizer` (or `learning_rate` for the default Adam), `n_iter`,
      `gradient` (``"auto"``, ``"reverse"`` or ``"forward"``, as above), `method`,
      `dt`, `n_steps`, `save_every`, `progress`
      as above; `weights`, `per_axis` and `checkpoint_every`
      belong to the default tracking cost and are not accepted.
    - `starts` (or `R0` / `Omega0`): initial states to average the cost over,
      ``1/B sum_b cost(simulate(..., R0=R0_b, Omega0=Omega0_b))``: attitudes of
      shape `(B, 3, 3)`, or a pair ``(R0, Omega0)`` with rates of shape `(3,)` or
      `(B, 3)` (default: the scene's own start). The runs are one `vmap`, and the
      gradient is the mean of the single-start gradients.

    **Returns:** a `TuneResult` (the best gains seen and the cost history).
    """
    import optax

    if starts is not None:
        if R0 is not None or Omega0 is not None:
            raise ValueError("pass the initial states either as starts or as R0/Omega0, not both")
        R0, Omega0 = starts if isinstance(starts, tuple | list) else (starts, None)
    if cost is not None:
        legacy = {
            "weights": weights is not None,
            "per_axis": per_axis,
            "checkpoint_every": checkpoint_every != "auto",
        }
        given = [k for k, v in legacy.items() if v]
        if given:
            raise ValueError(
                f"{', '.join(given)} belong(s) to the default tracking cost; with a custom "
                "cost, put the weights in the cost (starts= averages it over initial states)"
            )
        return _tune_general(
            scene,
            gains0,
            cost,
            method=RKMK4() if method is None else method,
            dt=dt,
            n_steps=n_steps,
            save_every=save_every,
            n_iter=n_iter,
            optimizer=optax.adam(learning_rate) if optimizer is None else optimizer,
            bounds=bounds,
            where=where,
            gradient=gradient,
            progress=progress,
            R0=R0,
            Omega0=Omega0,
        )
    if bounds is not None or where is not None:
        raise ValueError("bounds and where are for a custom cost (pass cost=...)")
    if gains0 is None:
        gains0 = (1.0, 1.0)
    _check_tracking_scene(scene)
    if method is None:
        method = RKMK4()
    n_iter = _check_int(n_iter, "n_iter", 0)
    _check_gradient(gradient)
    dtype = scene.y0.R.dtype
    if isinstance(gains0, GeometricGains):
        k_R0, k_O0 = gains0.k_R, gains0.k_Omega
    else:
        try:
            k_R0, k_O0 = gains0
        except (TypeError, ValueError):
            raise ValueError(
                f"gains0 must be a GeometricGains or a pair (k_R, k_Omega), got {gains0!r}"
            ) from None
    k_R0 = _gain_array(k_R0, "gains0.k_R", dtype)
    k_O0 = _gain_array(k_O0, "gains0.k_Omega", dtype)
    shape = (3,) if per_axis else ()
    if not per_axis and (k_R0.shape or k_O0.shape):
        raise ValueError("gains0 has per-axis gains: pass per_axis=True")
    theta = (
        jnp.log(jnp.broadcast_to(k_R0, shape)),
        jnp.log(jnp.broadcast_to(k_O0, shape)),
    )
    R0, Omega0 = _initial_batch(scene, R0, Omega0)
    if optimizer is None:
        optimizer = optax.adam(learning_rate)
    optimizer = optax.apply_if_finite(optimizer, max_consecutive_errors=5)
    opt_state = optimizer.init(theta)

    def loss(theta):
        k_R, k_O = jnp.exp(theta[0]), jnp.exp(theta[1])
        return expected_cost(
            scene,
            k_R,
            k_O,
            R0,
            Omega0,
            method,
            dt,
            n_steps,
            weights,
            save_every=save_every,
            checkpoint_every=checkpoint_every,
        )

    history, thetas, mode = _descend(
        loss, theta, optimizer, opt_state, n_iter, gradient, None, progress
    )
    cost = np.asarray(history)
    k_R_hist = np.exp(np.stack([np.asarray(t[0]) for t in thetas]))
    k_O_hist = np.exp(np.stack([np.asarray(t[1]) for t in thetas]))
    finite = np.where(np.isfinite(cost), cost, np.inf)
    best = int(np.argmin(finite))
    gains = GeometricGains(jnp.asarray(k_R_hist[best], dtype), jnp.asarray(k_O_hist[best], dtype))
    return TuneResult(
        gains=gains,
        cost=float(cost[best]),
        initial_cost=float(cost[0]),
        cost_history=cost,
        k_R_history=k_R_hist,
        k_Omega_history=k_O_hist,
        best_iteration=best,
        gradient=mode,
    )


#: `tune`'s ``gradient="auto"`` takes forward mode through at most this many tuned
#: scalars: the engine's ``forward_jacobian_max``, through which both modes are the same
#: one-pass Jacobian. Through more, reverse mode is the engine's discrete adjoint
#: (`so3jax._engine.derivatives.CheckpointedAdjoint`), several times faster than forward
#: mode through DiffTune's 12 quadrotor gains (``benchmarks/difftune.py``).
FORWARD_MODE_MAX = 8

_GRADIENTS = ("auto", "reverse", "forward")


def _check_gradient(gradient) -> None:
    if gradient not in _GRADIENTS:
        raise ValueError(f"gradient must be one of {_GRADIENTS}, got {gradient!r}")


def _resolve_gradient(gradient: str, params) -> str:
    """The mode `tune` runs for ``gradient`` and the tuned ``params`` (a pytree).

    ``"auto"`` is ``"forward"`` through at most `FORWARD_MODE_MAX` scalars and
    ``"reverse"`` beyond; ``"forward"`` and ``"reverse"`` are returned as given.
    """
    _check_gradient(gradient)
    if gradient != "auto":
        return gradient
    n = sum(int(np.size(x)) for x in jax.tree.leaves(params))
    return "forward" if n <= FORWARD_MODE_MAX else "reverse"


def _value_and_grad(loss, gradient: str):
    if gradient == "reverse":
        return jax.value_and_grad(loss)

    def fwd(params):
        grad, value = jax.jacfwd(lambda p: (loss(p),) * 2, has_aux=True)(params)
        return value, grad

    return fwd


def _descend(loss, params, optimizer, opt_state, n_iter, gradient, project, progress):
    """``n_iter`` jitted optimiser steps; returns the costs and the iterates (``n_iter + 1``),
    and the gradient's mode (`_resolve_gradient`).

    ``project`` (or ``None``) maps the updated parameters back into the feasible set.
    """
    import optax

    mode = _resolve_gradient(gradient, params)
    value_and_grad = _value_and_grad(loss, mode)

    @jit_own  # compiled with the engine's options for the library's own programs
    def step(params, opt_state):
        value, grad = value_and_grad(params)
        updates, opt_state = optimizer.update(grad, opt_state, params)
        params = optax.apply_updates(params, updates)
        if project is not None:
            params = project(params)
        return params, opt_state, value

    history, iterates = [], []
    iterator = range(n_iter)
    if progress:
        from tqdm.auto import tqdm

        iterator = tqdm(iterator, desc="tune", unit="it")
    for _ in iterator:
        iterates.append(params)
        params, opt_state, value = step(params, opt_state)
        history.append(float(value))
        if progress:
            iterator.set_postfix(cost=f"{history[-1]:.5g}")
    iterates.append(params)
    # The last cost from the compiled step (its update discarded): one more
    # iteration costs less than compiling the forward pass on its own.
    if n_iter:
        history.append(float(step(params, opt_state)[2]))
    else:
        history.append(float(jax.jit(loss)(params)))
    return history, iterates, mode


def _default_where(scene):
    if hasattr(scene, "gains"):
        return lambda s: s.gains
    if hasattr(getattr(scene, "controller", None), "gains"):
        return lambda s: s.controller.gains
    raise ValueError(f"scene {type(scene).__name__} has no gains to tune; pass where=lambda s: ...")


def _bound(value, params, name: str):
    if value is None:
        return None
    if jax.tree.structure(value) == jax.tree.structure(params):
        return value
    v = _as_float(value)
    if v.shape != ():
        raise ValueError(f"bounds ({name}) must be None, a scalar or a pytree like gains0")
    return jax.tree.map(lambda p: jnp.broadcast_to(v, jnp.shape(p)).astype(p.dtype), params)


def _tune_general(
    scene,
    gains0,
    cost,
    *,
    method,
    dt,
    n_steps,
    save_every,
    n_iter,
    optimizer,
    bounds,
    where,
    gradient,
    progress,
    R0=None,
    Omega0=None,
) -> TuneResult:
    import optax

    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a so3jax scene, got {type(scene).__name__}")
    if not callable(cost):
        raise TypeError(f"cost must be a function Trajectory -> scalar, got {cost!r}")
    if not isinstance(method, AbstractLieSolver):
        raise TypeError(f"method must be a so3jax Lie-group method, got {method!r}")
    _check_gradient(gradient)
    n_iter = _check_int(n_iter, "n_iter", 0)
    n_steps = _check_int(n_steps, "n_steps", 1)
    save_every = _check_int(save_every, "save_every", 1)
    where = _default_where(scene) if where is None else where
    present = where(scene)
    dtype = scene.y0.R.dtype
    params = present if gains0 is None else gains0
    if jax.tree.structure(params) != jax.tree.structure(present):
        raise ValueError(
            "gains0 must have the structure of the scene's gains "
            f"({jax.tree.structure(present)}), got {jax.tree.structure(params)}"
        )
    params = jax.tree.map(lambda p: jnp.asarray(p, dtype), params)
    # Checks that need concrete values (a quadrotor's dt against its control period),
    # here: inside the jitted tuning step the scene's arrays are traced. Under
    # `eval_shape` the scene, closed over, stays concrete for the checks, and nothing
    # is compiled or run.
    dt_checked = _check_dt(dt, dtype)
    jax.eval_shape(lambda: scene.for_step(dt_checked, jnp.zeros((), dtype)))
    if bounds is None:
        project = None
    else:
        try:
            lo, hi = bounds
        except (TypeError, ValueError):
            raise ValueError(f"bounds must be a pair (lower, upper), got {bounds!r}") from None
        lo, hi = _bound(lo, params, "lower"), _bound(hi, params, "upper")

        def project(p):
            if lo is not None:
                p = jax.tree.map(jnp.maximum, p, lo)
            if hi is not None:
                p = jax.tree.map(jnp.minimum, p, hi)
            return p

        params = project(params)

    batch = None if R0 is None and Omega0 is None else _initial_batch(scene, R0, Omega0)
    if batch is not None and _is_concrete(batch[0]):
        for b, R in enumerate(np.asarray(batch[0])):
            check_rotation(R, f"R0[{b}]")
        if not np.all(np.isfinite(np.asarray(batch[1]))):
            raise ValueError("Omega0 contains NaN or inf")

    def loss(p):
        from ._simulate import simulate

        sc = eqx.tree_at(where, scene, p)
        if batch is None:
            return cost(simulate(sc, method, dt, n_steps, save_every))

        def one(R, W):
            return cost(simulate(sc, method, dt, n_steps, save_every, R0=R, Omega0=W))

        return jnp.mean(jax.vmap(one)(*batch))

    optimizer = optax.apply_if_finite(optimizer, max_consecutive_errors=5)
    opt_state = optimizer.init(params)
    # One start: a single run, whose discrete adjoint keeps every step's residuals within
    # the policy's budget (`Policy.tune_residual_bytes`); a batch keeps checkpoints.
    budget = current().tune_residual_bytes
    scope = contextlib.nullcontext() if batch is not None else using(adjoint_residual_bytes=budget)
    with scope:
        history, iterates, mode = _descend(
            loss, params, optimizer, opt_state, n_iter, gradient, project, progress
        )
    costs = np.asarray(history)
    stacked = jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *iterates)
    best = int(np.argmin(np.where(np.isfinite(costs), costs, np.inf)))
    gains = iterates[best]

    def field(name):
        return np.asarray(getattr(stacked, name)) if hasattr(stacked, name) else None

    return TuneResult(
        gains=gains,
        cost=float(costs[best]),
        initial_cost=float(costs[0]),
        cost_history=costs,
        k_R_history=field("k_R"),
        k_Omega_history=field("k_Omega"),
        best_iteration=best,
        gains_history=stacked,
        gradient=mode,
    )
