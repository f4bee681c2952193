"""What a run returns: `Trajectory` and `Status`, and the argument checks every driver shares.

A module below both drivers, the fixed-step loop (`_simulate`) and the adaptive
one (`_adaptive`), so that neither imports the other to build its result.
"""

from __future__ import annotations

import operator

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._so3 import _is_concrete, _to_dtype
from ._state import LieState
from ._types import Array, Float, Int

#: Status codes of a run.
OK, NONFINITE, SOLVER_FAILED, MAX_STEPS = 0, 1, 2, 3
_MESSAGES = {
    OK: "finite to the end",
    NONFINITE: "the state stopped being finite",
    SOLVER_FAILED: "the implicit solve of a step did not converge",
    MAX_STEPS: "the step budget (max_steps) ran out before t1",
}


class Status(eqx.Module):
    """How a run ended.

    **Fields:**

    - `code`: 0 (finite to the end), 1 (the state stopped being finite), 2 (an
      implicit solve did not converge), 3 (adaptive runs: ``max_steps`` ran
      out); one per run under `vmap`.
    - `step`: index of the step that failed (the state at time
      ``t0 + step * dt`` was the last good one), or -1.

    After a failure the state is frozen at the last good value (a scene's
    time-driven rotations, such as the reference attitude ``Rd`` of a tracking
    scene, run on to the end) and the saved points past it are NaN, so a
    diverging run never poisons a batch.
    """

    code: Int[Array, "*batch"]
    step: Int[Array, "*batch"]

    @property
    def ok(self) -> Array:
        return self.code == OK

    def message(self) -> str:
        """A sentence for a single (unbatched) run."""
        code = int(self.code)
        if code == OK:
            return _MESSAGES[OK]
        return f"{_MESSAGES[code]} at step {int(self.step)}"


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
    conversion: under an active trace the conversion stages it, and a staged check
    would need `eqx.error_if`, whose host callback keeps JAX's persistent compilation
    cache from storing the program (`jax_compilation_cache_dir`). Only a ``dt`` that
    is itself traced (an argument of the caller's ``jit``) gets `eqx.error_if`.
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
    return eqx.error_if(dt, ~(dt > 0), "dt must be positive and finite")


def settling_time(t: Array, inside: Array) -> Array:
    """The first saved time after which ``inside`` holds at every later point.

    ``t`` and ``inside`` have shape `(n,)`; ``inf`` if ``inside`` is false at
    the last point.
    """
    n = inside.shape[0]
    last_out = jnp.max(jnp.where(~inside, jnp.arange(n), -1))
    return jnp.where(last_out < n - 1, t[jnp.minimum(last_out + 1, n - 1)], jnp.inf)
