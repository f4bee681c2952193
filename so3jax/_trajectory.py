"""What a run returns: `Trajectory` and `Status`, and the argument checks every driver shares.

A module below both drivers, the fixed-step loop (`_simulate`) and the adaptive
one (`_adaptive`), so that neither imports the other to build its result.
"""

from __future__ import annotations

import functools
import operator
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._scene import not_rotation
from ._so3 import _is_concrete, _to_dtype
from ._state import LieState, all_finite
from ._types import Array, Float, Int

#: Status codes of a run: what went wrong while stepping (1-3) ...
OK, NONFINITE, SOLVER_FAILED, MAX_STEPS = 0, 1, 2, 3
#: ... and what was wrong with the input before the first step (10-14) or inside a step (20).
BAD_DT, BAD_R0, BAD_RD0, NONFINITE_START, NONFINITE_PARAMETER = 10, 11, 12, 13, 14
COMMAND_UNDEFINED = 20
_MESSAGES = {
    OK: "finite to the end",
    NONFINITE: "the state stopped being finite",
    SOLVER_FAILED: "the implicit solve of a step did not converge",
    MAX_STEPS: "the step budget (max_steps) ran out before t1",
    BAD_DT: "dt is not positive and finite",
    BAD_R0: "the initial attitude R0 is not a rotation",
    BAD_RD0: "an initial reference attitude (Rd0) is not a rotation",
    NONFINITE_START: "the initial state holds NaN or inf",
    NONFINITE_PARAMETER: "a scene parameter (gains, inertia, reference, ...) is NaN or inf",
    COMMAND_UNDEFINED: (
        "the commanded attitude is undefined (b1_d parallel to the thrust axis b3c, "
        "or no commanded thrust)"
    ),
}
#: Codes of input that was bad before the first step: the run never started.
INPUT_CODES = (BAD_DT, BAD_R0, BAD_RD0, NONFINITE_START, NONFINITE_PARAMETER)


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" + ("" if n == 1 else "s")


class Status(eqx.Module):
    """How a run ended.

    **Fields:**

    - `code`: one per run under `vmap`; `Status.codes` maps each to its meaning:
        - 0: finite to the end;
        - 1: the state stopped being finite (a diverging closed loop, a step past
          the stability limit);
        - 2: an implicit solve did not converge (`LGVI`);
        - 3: adaptive runs: ``max_steps`` ran out before ``t1``;
        - 10-14: input that was bad before the first step, found under `jit` /
          `vmap` (eagerly the same input raises a `ValueError`): ``dt`` not positive
          and finite (10), ``R0`` not a rotation (11), a reference's ``Rd0`` not a
          rotation (12), NaN or inf in the initial state (13) or in a parameter of
          the scene such as a gain (14);
        - 20: a step met a commanded attitude that is undefined (the quadrotor's
          ``b1_d`` parallel to its thrust axis ``b3c``).
    - `step`: index of the step that failed (the state at time
      ``t0 + step * dt`` was the last good one), or -1 (no step failed, or the
      input was bad before the first step).
    - `t`: the time of the last good state (``t0 + step * dt``), NaN where no step
      failed; ``None`` for runs that do not record it.

    After a failure the state is frozen at the last good value (a scene's
    time-driven rotations, such as the reference attitude ``Rd`` of a tracking
    scene, run on to the end) and the saved points past it are NaN, so a
    diverging run never poisons a batch. A run whose input was bad is NaN from
    its first saved point.
    """

    code: Int[Array, "*batch"]
    step: Int[Array, "*batch"]
    t: Float[Array, "*batch"] | None = None

    #: The meaning of each code.
    codes: ClassVar[dict[int, str]] = _MESSAGES

    @property
    def ok(self) -> Array:
        return self.code == OK

    def message(self) -> str:
        """A sentence for a single run; for a batch, counts per outcome and the first failure.

        A batch's summary reads e.g. ``"62 of 64 runs finite to the end; 2 runs: the
        state stopped being finite; first failure: run 3, the state stopped being finite
        at step 118 (t = 1.18)"``.
        """
        code = np.asarray(self.code)
        step = np.asarray(self.step)
        t = None if self.t is None else np.asarray(self.t)
        if code.ndim == 0:
            return self._sentence(int(code), int(step), None if t is None else float(t))
        values, counts = np.unique(code, return_counts=True)
        parts = []
        for value, count in zip(values.tolist(), counts.tolist(), strict=True):
            if value == OK:
                parts.insert(0, f"{count} of {code.size} runs {_MESSAGES[OK]}")
            else:
                parts.append(f"{_plural(count, 'run')}: {self._describe(value)}")
        bad = np.argwhere(code != OK)
        if len(bad):
            i = tuple(int(j) for j in bad[0])
            first = self._sentence(int(code[i]), int(step[i]), None if t is None else float(t[i]))
            parts.append(f"first failure: run {i[0] if len(i) == 1 else i}, {first}")
        return "; ".join(parts)

    @staticmethod
    def _describe(code: int) -> str:
        return _MESSAGES.get(code, f"unknown status code {code}")

    @classmethod
    def _sentence(cls, code: int, step: int, t: float | None) -> str:
        text = cls._describe(code)
        if code == OK:
            return text
        if code in INPUT_CODES or step < 0:
            return f"{text} (before the first step)"
        where = f" at step {step}"
        if t is not None and np.isfinite(t):
            where += f" (t = {t:.6g})"
        return text + where


def status_from_diffrax(result, ok: Array, n_accepted: Array) -> Status:
    """`Status` of a `diffrax.diffeqsolve` run (``throw=False``).

    ``ok``: the saved states are finite; ``n_accepted``: accepted steps, reported
    as the failing step.
    """
    import diffrax

    ok = (result == diffrax.RESULTS.successful) & ok
    budget = result == diffrax.RESULTS.max_steps_reached
    code = jnp.where(ok, OK, jnp.where(budget, MAX_STEPS, NONFINITE)).astype(jnp.int32)
    return Status(code=code, step=jnp.where(ok, -1, n_accepted).astype(jnp.int32))


class Trajectory(eqx.Module):
    """Saved points of a run (index 0 is the initial state).

    **Fields:**

    - `t`: times, shape `(n_save,)`.
    - `R`: attitudes, shape `(n_save, 3, 3)`.
    - `Omega`: body angular velocities, shape `(n_save, 3)`.
    - `Rd`, `M`: reference attitude and control torque for tracking scenes
      (``None`` otherwise).
    - `extras`: any other quantities the scene observes, by name.
    - `status`: a `Status`.
    - `y`: the final state (a `LieState`), for restarting.
    """

    t: Float[Array, "*batch n"]
    R: Float[Array, "*batch n 3 3"]
    Omega: Float[Array, "*batch n 3"]
    status: Status
    y: LieState
    Rd: Float[Array, "*batch n 3 3"] | None = None
    M: Float[Array, "*batch n 3"] | None = None
    extras: dict = eqx.field(default_factory=dict)


def _trajectory(t, obs: dict, status: Status, y: LieState) -> Trajectory:
    obs = dict(obs)
    fields = {k: obs.pop(k) for k in ("R", "Omega", "Rd", "M") if k in obs}
    return Trajectory(t=t, status=status, y=y, extras=obs, **fields)


def _check_int(value, name: str, minimum: int) -> int:
    try:
        v = operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be an integer, got {value!r}") from None
    if v < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {v}")
    return v


def _check_dt(dt, dtype) -> Array:
    """``dt`` as a scalar of ``dtype``, checked positive and finite.

    A concrete value (a Python float, a NumPy or JAX array) is checked here, before
    conversion: under an active trace the conversion stages it. A ``dt`` that is
    itself traced (an argument of the caller's ``jit`` or ``vmap``) is checked in
    the run instead: the run's `Status` says ``BAD_DT`` and its points are NaN.
    """
    if _is_concrete(dt):
        with np.errstate(over="ignore", under="ignore"):  # in the run's dtype: 1e-50 is 0
            v = np.asarray(dt, dtype)  # in float32, 1e300 is inf
        if v.shape != ():
            raise ValueError(f"dt must be a scalar, got shape {v.shape}")
        if not np.isfinite(float(v)) or float(v) <= 0:
            raise ValueError(f"dt must be positive and finite, got {float(v)}")
        return _to_dtype(v, dtype)
    dt = _to_dtype(dt, dtype)
    if dt.shape != ():
        raise ValueError(f"dt must be a scalar, got shape {dt.shape}")
    return dt


def input_code(scene, dt, groups, x: Array) -> Array:
    """The `Status` code of a run's input, checked in the traced program (0: good).

    Eagerly, bad values raise a `ValueError` before tracing; under `jit` / `vmap`
    a run with bad input starts with this code, so its state stays frozen and its
    saved points are NaN, while the other runs of a batch go on untouched. In
    order: ``dt`` not positive and finite, a non-finite initial state, a body
    attitude or a reference attitude that is not a rotation, a non-finite
    parameter of the scene (gains, inertia, reference).

    The initial state comes as its rotation groups (a sequence of `(3, 3)` arrays)
    and vector part ``x``: each group is checked apart, so a group that a batch's
    runs share (a reference attitude) is checked once, not once per run.
    """
    params = jax.tree.leaves(
        eqx.filter(eqx.tree_at(lambda s: s.y0, scene, None), eqx.is_inexact_array)
    )
    finite = [jnp.all(jnp.isfinite(a)) for a in params]
    not_rot = [not_rotation(R) for R in groups]
    checks = [
        (~(jnp.isfinite(dt) & (dt > 0)), BAD_DT),
        (~all_finite((tuple(groups), x)), NONFINITE_START),
        (not_rot[0], BAD_R0),
        (functools.reduce(jnp.logical_or, not_rot[1:], jnp.array(False)), BAD_RD0),
        (~functools.reduce(jnp.logical_and, finite, jnp.array(True)), NONFINITE_PARAMETER),
    ]
    code = jnp.array(OK, jnp.int32)
    for bad, value in reversed(checks):  # the first that holds wins
        code = jnp.where(bad, jnp.int32(value), code)
    return code


def mark_bad_input(traj: Trajectory, code0: Array) -> Trajectory:
    """``traj`` with a run whose input code ``code0`` is not OK marked: its status says
    ``code0`` (step -1) and its saved points and final state are NaN (float leaves;
    counters such as the number of steps stay)."""
    started = code0 == OK
    s = traj.status
    status = Status(
        code=jnp.where(started, s.code, code0),
        step=jnp.where(started, s.step, -1),
        t=None if s.t is None else jnp.where(started, s.t, jnp.nan),
    )
    return Trajectory(
        t=traj.t,
        R=_nan_unless(started, traj.R),
        Omega=_nan_unless(started, traj.Omega),
        status=status,
        y=_nan_unless(started, traj.y),
        Rd=_nan_unless(started, traj.Rd),
        M=_nan_unless(started, traj.M),
        extras=_nan_unless(started, traj.extras),
    )


def _nan_unless(keep: Array, tree):
    """``tree`` where ``keep``, its float leaves NaN elsewhere (integer leaves, such as
    step counters, stay)."""
    return jax.tree.map(
        lambda a: jnp.where(keep, a, jnp.nan) if jnp.issubdtype(a.dtype, jnp.inexact) else a,
        tree,
    )


def settling_time(t: Array, inside: Array) -> Array:
    """The first saved time after which ``inside`` holds at every later point.

    ``t`` and ``inside`` have shape `(n,)`; ``inf`` if ``inside`` is false at
    the last point.
    """
    n = inside.shape[0]
    last_out = jnp.max(jnp.where(~inside, jnp.arange(n), -1))
    return jnp.where(last_out < n - 1, t[jnp.minimum(last_out + 1, n - 1)], jnp.inf)
