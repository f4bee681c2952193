"""Every JAX internal so3jax's engine touches, behind one version gate.

- `set_xla_metadata`: tags a loop so XLA's CPU compiler builds it as one kernel
  (`so3jax._engine.passes.hoist._hoisted`);
- ``BatchTracer``: whether a value closed over is batched by an enclosing ``vmap`` (`batched`);
- the rule tables of so3jax's own primitive (`so3jax._engine.linear_call`).

On a JAX release outside `TESTED`, or without those tables (`supported` is False), the
engine runs its reference programs and warns once (`warn_reference_path`). Nothing here
changes JAX's state.
"""

from __future__ import annotations

import functools
import warnings

import jax

from .linear_call import AVAILABLE as _HAVE_LINEAR_CALL

#: The JAX releases (major, minor) the suite passes on with the engine's fast paths.
TESTED = frozenset({(0, 10), (0, 11), (0, 12)})

#: The jaxlib releases whose XLA compiles the suite's loops as one kernel on a CPU (the
#: ``"hoist"`` pass, on by default there only: `so3jax._engine.policy.hoisting_verified`).
#: XLA aborts the process where it cannot compile one; JAX 0.11's does on a ``vmap`` of a
#: gradient ("All or none of the slices should have an explicit index",
#: ``tests/test_engine.py::test_vmap_of_grad_equals_loop_of_grads``).
HOIST_TESTED = frozenset({(0, 10), (0, 12)})

try:
    from jax.experimental.xla_metadata import set_xla_metadata
except ImportError:  # pragma: no cover - an older JAX: loops compile as XLA decides
    set_xla_metadata = None

try:
    from jax._src.interpreters import batching as _batching

    _BatchTracer = _batching.BatchTracer
except (ImportError, AttributeError):  # pragma: no cover - JAX moved it
    _batching, _BatchTracer = None, None


def release() -> tuple[int, int]:
    """The installed JAX's (major, minor) release."""
    try:
        return tuple(int(x) for x in jax.__version__.split(".")[:2])
    except ValueError:  # pragma: no cover - a version string of another form
        return (0, 0)


def supported() -> bool:
    """Whether the installed JAX is one of `TESTED`, with the rule tables so3jax's own
    ``linear_call`` needs (the engine's fast paths are on)."""
    return release() in TESTED and _HAVE_LINEAR_CALL


@functools.cache
def warn_reference_path() -> None:
    """Warn, once per process, that the engine runs its reference programs."""
    warnings.warn(
        f"so3jax: JAX {jax.__version__} is not one of the releases so3jax's engine is "
        f"tested on ({', '.join(f'{a}.{b}' for a, b in sorted(TESTED))}); runs take the "
        "reference path (the checkpointed lax.scan and JAX's own autodiff): the same "
        "results, without the scalarized batch layout, the one-pass Jacobian and the "
        "one-kernel loops (several times slower in batches and gradients)",
        stacklevel=3,
    )


def batched(x) -> bool:
    """Whether ``x`` is batched by an enclosing ``vmap`` (a batch tracer with a batch axis).

    An unbatched axis is ``not_mapped`` (JAX <= 0.9) or ``None``. Without JAX's batch tracer,
    any tracer counts as batched (the safe answer).
    """
    if _BatchTracer is None:  # pragma: no cover - JAX moved it
        return isinstance(x, jax.core.Tracer)
    if not isinstance(x, _BatchTracer):
        return False
    axis = x.batch_dim
    return axis is not None and axis is not getattr(_batching, "not_mapped", None)
