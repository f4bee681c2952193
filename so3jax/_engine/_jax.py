"""Every JAX internal so3jax's engine touches, behind one version gate.

The engine's fast paths lean on parts of JAX that are not its stable API:

- `jax.experimental.xla_metadata.set_xla_metadata`, which tags a loop so that XLA's
  CPU compiler builds it as one kernel (`so3jax._engine._hoisted`);
- `jax._src.interpreters.batching.BatchTracer`, to tell whether a value closed over
  by a program is batched by an enclosing ``vmap`` (`batched`);
- the rule tables for a primitive of so3jax's own (`so3jax._engine.linear_call`, which
  checks its own names).

`TESTED` lists the JAX releases the test suite passes on with them. On another
release (`supported` is False) the engine runs its reference programs: JAX's own
autodiff of the checkpointed ``lax.scan``, no scalarized layout, no hoisted loops.
It warns once, naming what that costs (`warn_reference_path`). Nothing here changes
JAX's state.
"""

from __future__ import annotations

import functools
import warnings

import jax

#: The JAX releases (major, minor) the suite passes on with the engine's fast paths.
TESTED = frozenset({(0, 10), (0, 11), (0, 12)})

try:  # frontend attributes on the ops traced inside (`so3jax._engine._hoisted`)
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
    """Whether the installed JAX is one of `TESTED` (the engine's fast paths are on)."""
    return release() in TESTED


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

    JAX up to 0.9 marks an unbatched tracer's axis with the sentinel ``not_mapped``; 0.10
    and later with ``None``. Where JAX's batch tracer cannot be found, any tracer counts
    as batched (the safe answer: a batched layout for a value that is not).
    """
    if _BatchTracer is None:  # pragma: no cover - JAX moved it
        return isinstance(x, jax.core.Tracer)
    if not isinstance(x, _BatchTracer):
        return False
    axis = x.batch_dim
    return axis is not None and axis is not getattr(_batching, "not_mapped", None)
