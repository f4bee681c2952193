"""Every threshold and switch of the engine, in one frozen object.

A `Policy` names the optimisation passes that run (`PASSES`) and every number the engine
decides by. The engine reads the active policy at trace time (`current`); `using`
activates another for a block, in the current thread and context only:

    with so3jax._engine.policy.using(passes=frozenset()):  # the reference path
        ...

`DEFAULT` is built once at import from the fields' defaults and three environment
variables, never read again:

- ``SO3JAX_PASSES``: ``all`` (default), ``none``, or comma-separated names from `PASSES`;
- ``SO3JAX_HOIST_LOOPS``: ``0`` or ``1``, the ``"hoist"`` pass off or on whatever
  `hoisting_verified` says;
- ``SO3JAX_FRAME_TANGENTS``: ``0`` turns the ``"frames"`` pass off.

so3jax's jitted entry points key their programs by the policy (`so3jax._engine.plan.jit`);
a function the caller already traced keeps its trace (docs/engine.md, "Where the code
lives"). Each pass proves its equality with the reference in ``tests/passes/``;
``benchmarks/ablation.py`` measures what it buys.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import os
import warnings

import jax

from . import _jax

__all__ = ["PASSES", "Policy", "DEFAULT", "current", "using"]

#: The optimisation passes, each a module of `so3jax._engine.passes`: ``"scalarize"``
#: (a large batch as the structure-of-arrays program), ``"cuts"`` (fusion cuts), ``"frames"``
#: (attitude tangents as three numbers), ``"hoist"`` (each loop one CPU kernel), ``"unroll"``
#: (small reductions written out), ``"tiles"`` (Jacobian batches in cache-sized tiles),
#: ``"settle"`` (loops start at JAX's fixed point over their carry). With none, a run is
#: the array program, vmapped by JAX; derivatives keep their strategy.
PASSES = frozenset({"scalarize", "cuts", "frames", "hoist", "unroll", "tiles", "settle"})


def hoisting_verified() -> bool:
    """Whether the installed jaxlib is a release the suite passes on with loops hoisted
    (`so3jax._engine._jax.HOIST_TESTED`): where XLA cannot compile one, it aborts the process."""
    try:
        import jaxlib

        release = tuple(int(x) for x in jaxlib.__version__.split(".")[:2])
    except (ImportError, AttributeError, ValueError):
        return False
    return release in _jax.HOIST_TESTED


@dataclasses.dataclass(frozen=True)
class Policy:
    """The engine's thresholds and switches (frozen and hashable: a jit cache key).

    Tables are tuples of ``(key, value)`` pairs (a dict is converted); read them through
    the methods. Batch-size thresholds are numbers of runs; ``None`` means never.
    """

    #: The passes that run (`PASSES`).
    passes: frozenset = PASSES
    #: Per program, ``(s, c)``: scalarized from ``s`` runs, fusion cuts (CPU) from ``c``;
    #: ``"jvp"``: second derivatives; ``"scalar"``/``"array"``: ``program=`` forced; no entry:
    #: always the array program. Where scalarizing repays its compile (``benchmarks/layouts.py``).
    batched_layout: tuple = (
        ("run", (16, 16)),
        ("scalar", (1, 64)),
        ("jacobian", (16, 16)),
        ("array", (None, None)),
        ("jvp", (32, 32)),
    )
    #: On a GPU, the entries that differ from `batched_layout`: where 100 calls, compile
    #: included, beat the array program (``benchmarks/layouts.py``; ``results/layouts-*gpu*.json``).
    gpu_layout: tuple = (
        ("run", (32768, None)),
        ("jacobian", (16384, None)),
        ("jvp", (4096, None)),
    )
    #: `so3jax.sweep`'s default runs per chunk per device, by platform: where throughput
    #: stops growing (``benchmarks/sweep.py``).
    sweep_chunk: tuple = (("cpu", 1024), ("gpu", 65536))
    #: Whether `so3jax.sweep` scalarizes its chunks by default, by platform
    #: (``benchmarks/sweep.py``).
    sweep_scalarize: tuple = (("cpu", True), ("gpu", False))
    #: XLA options, by platform, for the programs so3jax compiles itself
    #: (`so3jax._tune.jit_own`; ``benchmarks/tune.py``). ``XLA_FLAGS`` wins.
    own_compiler_options: tuple = (("cpu", (("xla_backend_optimization_level", 2),)),)
    #: Values per scalar component in one ``"tiles"`` tile, ``m (1 + n)`` for ``m`` runs and
    #: ``n`` columns: sized to the core's cache (``benchmarks/layouts.py``).
    tile_values: int = 192
    #: Tiles only for runs observing at most this many scalars per saved point (docs/engine.md,
    #: "Tiles").
    tile_max_observed: int = 8
    #: Tiles are a multiple of this many runs (float64 lanes of an AVX-512 register).
    tile_multiple: int = 8
    #: The step loops' ``lax.scan`` ``unroll`` (``benchmarks/unroll.py``).
    scan_unroll: int = 1
    #: The largest input leaf of a hoisted loop, in bytes over the batch: past it XLA's
    #: threads pay (``benchmarks/emitters.py``).
    hoist_max_bytes: int = 64 * 1024
    #: The largest array a hoisted loop makes in its body, in bytes over the batch: from there
    #: XLA splits an operation on it across threads, which a hoisted kernel cannot link
    #: (``tests/passes/test_pass_hoist.py``).
    hoist_max_inner: int = 8 * 2**20
    #: The most elements a reduction in a hoisted loop may read over the batch, past which
    #: XLA's older CPU emitter fails
    #: (``tests/test_engine.py::test_hoisting_keeps_out_what_one_kernel_cannot_hold``).
    hoist_max_reduced: int = 1024
    #: The most terms of a reduction the ``"unroll"`` pass writes out (3x3 products, Frobenius
    #: products; ``tests/test_engine.py::test_small_reductions_written_out_term_by_term``).
    unroll_max_terms: int = 27
    #: A value with several consumers is cut (``"cuts"``) when XLA would recompute at least
    #: this many operations for each (docs/engine.md, "Fusion cuts").
    cut_cone: int = 8
    #: The cone, in operations, from which values tangent columns consume are cut
    #: (``benchmarks/element_work.py``).
    column_cut_cone: int = 4
    #: Column cuts in the scalarized Jacobian program from this many runs
    #: (``tests/test_engine.py::test_scalarized_jacobian_cuts_what_its_columns_consume``).
    column_cuts_from: int = 32
    #: The longest table a scalarized derivative program reads by ``lax.dynamic_slice`` (a
    #: `so3jax.Gust`'s path), each entry a carried scalar; longer: the array program
    #: (``tests/passes/test_pass_scalarize.py::test_a_long_table_runs_the_array_program``).
    scalarize_table_max: int = 128
    #: The most differentiated scalars for the one-pass Jacobian
    #: (`so3jax._engine.derivatives.OnePassJacobian`; ``tests/test_explain.py``).
    forward_jacobian_max: int = 8
    #: Bytes per run within which `so3jax._engine.derivatives.CheckpointedAdjoint`
    #: keeps every step's residuals; past it, and at 0, checkpointed segments, memory
    #: ``~ sqrt(n_steps)`` (``benchmarks/adjoint.py``).
    adjoint_residual_bytes: int = 0
    #: `adjoint_residual_bytes` for `so3jax.tune` with one start
    #: (``tests/test_explain.py::test_grad_through_twelve_gains_is_the_discrete_adjoint``).
    tune_residual_bytes: int = 32 * 2**20

    def __post_init__(self):
        unknown = set(self.passes) - PASSES
        if unknown:
            raise ValueError(f"passes: unknown {sorted(unknown)}; known: {sorted(PASSES)}")
        object.__setattr__(self, "passes", frozenset(self.passes))
        for field in ("batched_layout", "gpu_layout", "sweep_chunk", "sweep_scalarize"):
            value = getattr(self, field)
            if isinstance(value, dict):  # a table given as a dict (`using`, tests)
                object.__setattr__(self, field, tuple(value.items()))
        options = self.own_compiler_options
        if isinstance(options, dict):
            pairs = ((k, tuple(dict(v).items())) for k, v in options.items())
            object.__setattr__(self, "own_compiler_options", tuple(pairs))

    def on(self, name: str) -> bool:
        """Whether pass ``name`` (one of `PASSES`) runs."""
        return name in self.passes

    def layout(self, what: str) -> tuple:
        """``(s, c)`` for program ``what`` on the default backend: ``(None, None)`` without
        an entry or ``"scalarize"``; ``c = None`` without ``"cuts"``."""
        table = dict(self.batched_layout)
        if jax.default_backend() == "gpu":
            table.update(self.gpu_layout)
        s, c = table.get(what, (None, None))
        if not self.on("scalarize"):
            return None, None
        return s, (c if self.on("cuts") else None)

    def chunk(self, platform: str) -> int:
        return dict(self.sweep_chunk)[platform]

    def compiler_options(self, platform: str) -> dict:
        return dict(dict(self.own_compiler_options).get(platform, ()))

    def replace(self, **changes) -> Policy:
        """A copy with ``changes`` (field names)."""
        return dataclasses.replace(self, **changes)


def _from_env() -> Policy:
    """`DEFAULT`, from the environment variables of the module docstring."""
    asked = os.environ.get("SO3JAX_PASSES", "all").strip().lower()
    if asked in ("", "all"):
        passes = set(PASSES)
    elif asked == "none":
        passes = set()
    else:
        passes = {p.strip() for p in asked.split(",") if p.strip()}
        unknown = passes - PASSES
        if unknown:
            warnings.warn(
                f"so3jax: SO3JAX_PASSES names unknown passes {sorted(unknown)}; "
                f"known: {sorted(PASSES)}",
                stacklevel=2,
            )
            passes &= PASSES
    hoist = os.environ.get("SO3JAX_HOIST_LOOPS")
    if (hoisting_verified() if hoist is None else hoist != "0") is False:
        passes.discard("hoist")
    if os.environ.get("SO3JAX_FRAME_TANGENTS", "1") == "0":
        passes.discard("frames")
    return Policy(passes=frozenset(passes))


#: The policy in force unless `using` says otherwise (built once at import).
DEFAULT = _from_env()

#: Whether the ``"hoist"`` pass is held back because the installed jaxlib is not verified
#: for it (`hoisting_verified`) and ``SO3JAX_HOIST_LOOPS`` is unset: the first loop on one
#: CPU device then warns (`so3jax._engine.passes.hoist.warn_held_back`).
HOIST_HELD_BACK = "SO3JAX_HOIST_LOOPS" not in os.environ and not hoisting_verified()

_ACTIVE: contextvars.ContextVar[Policy] = contextvars.ContextVar("so3jax_policy", default=DEFAULT)


def current() -> Policy:
    """The active policy (`DEFAULT` outside `using`)."""
    return _ACTIVE.get()


@contextlib.contextmanager
def using(policy: Policy | None = None, **changes):
    """Run a block under ``policy`` (default: the active one) with ``changes``, e.g.
    ``passes=frozenset()`` (the reference path) or ``passes=PASSES - {"hoist"}``."""
    new = (policy or current()).replace(**changes)
    token = _ACTIVE.set(new)
    try:
        yield new
    finally:
        _ACTIVE.reset(token)


# --------------------------------------------------------------------------
# decisions read from the policy
# --------------------------------------------------------------------------


def one_cpu_device() -> bool:
    """Whether JAX runs on one CPU device, where hoisted loops and tiles apply."""
    return jax.default_backend() == "cpu" and jax.device_count() == 1


def batched_layout(what: str) -> tuple:
    """``(s, c)`` for program ``what`` under the active policy (`Policy.layout`)."""
    return current().layout(what)
