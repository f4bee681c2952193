"""Every threshold and switch of the engine, in one frozen object.

A `Policy` says which optimisation passes run (`PASSES`) and every number the engine
decides by: the batch sizes from which a program runs scalarized, tiles, the largest
hoisted loop, the most scalars differentiated in one pass. The engine reads the
active policy at trace time (`current`); `using` activates another for a block of
code, in the current thread and context only:

    with so3jax._engine.policy.using(passes=frozenset()):  # the reference path
        ...

The default (`DEFAULT`) is built once at import, from the tables below and three
environment variables, read then and never again:

- ``SO3JAX_PASSES``: ``all`` (the default), ``none``, or the comma-separated names of
  the passes to run (`PASSES`);
- ``SO3JAX_HOIST_LOOPS``: ``0`` or ``1``, the ``"hoist"`` pass off or on whatever
  `hoisting_verified` says;
- ``SO3JAX_FRAME_TANGENTS``: ``0`` turns the ``"frames"`` pass off.

so3jax's jitted entry points key their compiled programs by the active policy
(`so3jax._engine.plan.jit`), so a call under another policy traces again, under that
policy. A function of the caller's that JAX has already traced (``jax.jit``,
``jax.make_jaxpr``) keeps its trace, as it would keep any value read while tracing: a
new function, or `jax.clear_caches`, sees the new policy (``benchmarks/_common.py``'s
``engine_settings`` clears the caches). Each pass
proves its equality with the reference path in ``tests/passes/``; what each one buys
is measured by ``benchmarks/ablation.py``.
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

#: The engine's optimisation passes, each a module of `so3jax._engine.passes`:
#:
#: - ``"scalarize"``: a large batch runs as the structure-of-arrays program;
#: - ``"cuts"``: fusion cuts where XLA on CPU would recompute shared values;
#: - ``"frames"``: attitude tangents as three numbers in the Jacobian programs;
#: - ``"hoist"``: each loop one kernel on a CPU;
#: - ``"unroll"``: small reductions written out term by term (so derivative loops hoist);
#: - ``"tiles"``: a large batch of Jacobian programs in cache-sized tiles;
#: - ``"settle"``: each loop starts with the carry batched and differentiated as JAX's
#:   fixed point over its body would end, so that JAX transforms the body once.
#:
#: With none of them, a run executes the array program (``lax.scan`` of the step as
#: written), vmapped by JAX under ``vmap``; derivatives keep their strategy
#: (`so3jax._engine.derivatives`).
PASSES = frozenset({"scalarize", "cuts", "frames", "hoist", "unroll", "tiles", "settle"})


def hoisting_verified() -> bool:
    """Whether the installed jaxlib is one of the releases the suite passes on with loops
    hoisted (`so3jax._engine._jax.TESTED`): XLA's older emitter aborts the process, not
    raises, where it cannot compile a hoisted loop."""
    try:
        import jaxlib

        release = tuple(int(x) for x in jaxlib.__version__.split(".")[:2])
    except (ImportError, AttributeError, ValueError):
        return False
    return release in _jax.TESTED


@dataclasses.dataclass(frozen=True)
class Policy:
    """The engine's thresholds and switches (frozen and hashable: a jit cache key).

    Tables are tuples of ``(key, value)`` pairs (a dict given for one is converted);
    read them through the methods. Batch-size thresholds are numbers of runs; ``None``
    means never.
    """

    #: The passes that run (`PASSES`).
    passes: frozenset = PASSES
    #: How each program runs under ``vmap``, by batch size: ``(s, c)`` runs the
    #: scalarized program for batches of ``s`` runs or more (the array program, vmapped,
    #: below that) and cuts its fusion (CPU only) from ``c`` runs on. ``"scalar"`` and
    #: ``"array"`` are ``program="scalar"`` and ``"array"`` (benchmarks); ``"jvp"``: the
    #: programs of second derivatives; a program without an entry (the discrete adjoint)
    #: always runs the array program. Each entry is where the scalarized program pays
    #: for its longer compile within the calls a sweep or a `tune` makes, on a 2-core CPU
    #: with each loop one kernel; measured by ``benchmarks/layouts.py``.
    batched_layout: tuple = (
        ("run", (16, 16)),
        ("scalar", (1, 64)),
        ("jacobian", (16, 16)),
        ("array", (None, None)),
        ("jvp", (32, 32)),
    )
    #: On a GPU, the entries that differ from `batched_layout`. A GPU is latency bound in
    #: either layout up to a few thousand runs, where the scalarized program compiles
    #: several times longer: each entry scalarizes from where 100 calls with their compile
    #: take less time than the array program's (``benchmarks/layouts.py`` on the GPUs
    #: named in ``benchmarks/results/layouts-*gpu*.json``).
    gpu_layout: tuple = (
        ("run", (32768, None)),
        ("jacobian", (16384, None)),
        ("jvp", (4096, None)),
    )
    #: `so3jax.sweep`'s runs per chunk per device when none is given: a 2-core CPU is
    #: throughput bound from a few hundred runs; a GPU is latency bound up to tens of
    #: thousands (``benchmarks/sweep.py``).
    sweep_chunk: tuple = (("cpu", 1024), ("gpu", 65536))
    #: Whether `so3jax.sweep` steps its chunks scalarized by default, per platform: on a
    #: GPU the compiled sweep runs about as fast in either layout and the array program
    #: compiles several times faster (``benchmarks/sweep.py``).
    sweep_scalarize: tuple = (("cpu", True), ("gpu", False))
    #: XLA's options for the programs the library compiles itself (`so3jax._tune.jit_own`), per
    #: platform: LLVM's ``-O2`` on CPU compiles hoisted loops faster and runs small
    #: scalarized batches faster (``benchmarks/tune.py``). ``XLA_FLAGS`` wins.
    own_compiler_options: tuple = (("cpu", (("xla_backend_optimization_level", 2),)),)
    #: Values per scalar component in one tile of a batched Jacobian program (``"tiles"``):
    #: a tile of ``m`` runs with ``n`` columns holds ``m (1 + n)``; a tile's values stay
    #: in the core's cache where a whole batch's do not (``benchmarks/layouts.py``).
    tile_values: int = 192
    #: Tiles only for runs observing at most this many scalars per saved point (a cost's
    #: integrand): where saved points dominate, tiles cost memory and do not pay.
    tile_max_observed: int = 8
    #: Tiles are a multiple of this many runs (float64 lanes of an AVX-512 register).
    tile_multiple: int = 8
    #: Steps per iteration of the step loops' ``lax.scan`` (its ``unroll``;
    #: ``benchmarks/unroll.py``).
    scan_unroll: int = 1
    #: The largest input leaf of a hoisted loop, in bytes over a batch's runs: one
    #: kernel gives up XLA's threads, which pay past that (``benchmarks/emitters.py``).
    hoist_max_bytes: int = 64 * 1024
    #: The largest array a hoisted loop makes inside its body (a segment's stacked
    #: residuals, say), in bytes over a batch's runs: from 8 MiB XLA's CPU compiler splits
    #: an operation on it across threads, which a hoisted kernel cannot call (the program
    #: fails to link ``__xla_cpu_runtime_ParallelForkJoin``:
    #: ``tests/passes/test_pass_hoist.py``).
    hoist_max_inner: int = 8 * 2**20
    #: The most elements a reduction in a hoisted loop may read over the batch: past it
    #: XLA makes a fusion kind its older CPU emitter does not implement.
    hoist_max_reduced: int = 1024
    #: The most terms of a reduction the ``"unroll"`` pass writes out (27: the 3-term sums
    #: of 3x3 products, the 9-term sums of a Frobenius product).
    unroll_max_terms: int = 27
    #: A value with several consumers is cut (``"cuts"``) when XLA would recompute at
    #: least this many operations for each of them (seed batches: 6 to 10 run alike).
    cut_cone: int = 8
    #: The cone from which values that tangent columns consume are cut
    #: (``benchmarks/element_work.py``).
    column_cut_cone: int = 4
    #: Column cuts in the scalarized Jacobian program from batches of this many runs.
    column_cuts_from: int = 32
    #: The longest table (entries along a computed index) that a scalarized derivative
    #: program reads by ``lax.dynamic_slice`` (a `so3jax.Gust`'s path): there each entry
    #: is a scalar component the loop carries, so its run and compile time grow with the
    #: table; a longer one runs the array program. (The forward program keeps a run's
    #: tables whole: `scalarize.is_table`.)
    scalarize_table_max: int = 128
    #: Through at most this many differentiated scalars a run computes its Jacobian with
    #: its value in one pass (`so3jax._engine.derivatives.OnePassJacobian`).
    forward_jacobian_max: int = 8
    #: The discrete adjoint (`so3jax._engine.derivatives.CheckpointedAdjoint`) keeps every
    #: step's residuals from the run's forward pass while they take at most this many
    #: bytes per run (memory linear in ``n_steps``): its backward pass then replays no
    #: step, and its program is smaller to compile. Past it (and at 0, the
    #: default), checkpointed segments, memory ``~ sqrt(n_steps)``, each replayed
    #: backward. Not the default: the rule cannot see a ``vmap`` around it, and batched
    #: the residuals' program runs slower than the segments (``benchmarks/adjoint.py``).
    adjoint_residual_bytes: int = 0
    #: `adjoint_residual_bytes` for `so3jax.tune`'s iteration with one start, a single run
    #: by construction.
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
        """``(s, c)`` for program ``what`` on the default backend; ``(None, None)`` (the
        array program always) for a program without an entry and with the ``"scalarize"``
        pass off; ``c = None`` with ``"cuts"`` off."""
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
    """`DEFAULT`: the tables above and ``SO3JAX_PASSES``, ``SO3JAX_HOIST_LOOPS``,
    ``SO3JAX_FRAME_TANGENTS`` (read once, here)."""
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

_ACTIVE: contextvars.ContextVar[Policy] = contextvars.ContextVar("so3jax_policy", default=DEFAULT)


def current() -> Policy:
    """The active policy (`DEFAULT` outside `using`)."""
    return _ACTIVE.get()


@contextlib.contextmanager
def using(policy: Policy | None = None, **changes):
    """Run a block under ``policy`` (default: the active one) with ``changes``.

    ``using(passes=frozenset())`` is the reference path; ``using(passes=PASSES -
    {"hoist"})`` everything but one pass.
    """
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
    """Whether JAX runs on one CPU device: where the engine's CPU-only choices (hoisted
    loops, tiles) apply. A sharded program is XLA's to partition."""
    return jax.default_backend() == "cpu" and jax.device_count() == 1


def batched_layout(what: str) -> tuple:
    """``(s, c)`` for program ``what`` under the active policy (`Policy.layout`)."""
    return current().layout(what)
