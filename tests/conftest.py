"""Test configuration: float64 on for the suite (the library itself never touches it)."""

import gc
import os
import subprocess
import sys

os.environ.setdefault("MPLBACKEND", "Agg")

#: XLA settings for the suite's CPU compilations, which take most of its time:
#:
#: - XLA's CPU compiler has two code generators for fused kernels: the MLIR "fusion
#:   emitters" (its default) and the older LLVM IR emitters. On the suite's 2-core CPU the
#:   older ones compile the library's programs faster and run them as fast or faster, so
#:   the whole suite takes markedly less time (`benchmarks/emitters.py`).
#: - LLVM's optimisation level 0 instead of 3: the tests' programs run for milliseconds,
#:   so optimising their machine code costs more than it saves (every module takes less
#:   time); the few tests that run long enough for optimised code to pay ask for level 3
#:   per program (the million-step runs of ``test_integrators.py``).
#:
#: Every worker and notebook kernel inherits this process's XLA_FLAGS. A flag the jaxlib
#: no longer knows is left out (JAX 0.11's XLA rejects the first); the caller's own
#: XLA_FLAGS win, and SO3JAX_TEST_XLA_DEFAULTS=1 asks for XLA's defaults. Results agree to
#: round-off either way; nothing in the library depends on these settings.
XLA_CPU_FLAGS = ("--xla_cpu_use_fusion_emitters=false", "--xla_backend_optimization_level=0")


def _xla_accepts(flags: str) -> bool:
    """Whether a fresh process starts XLA's CPU client with these XLA_FLAGS.

    (An unknown flag aborts the process that reads it, so it is tried in another.)
    """
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    code = "import jax; jax.numpy.zeros(1).block_until_ready()"
    try:
        probe = subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, timeout=120
        )
    except subprocess.TimeoutExpired:
        return False
    return probe.returncode == 0


def _choose_xla_flags() -> None:
    if os.environ.get("PYTEST_XDIST_WORKER") or os.environ.get("SO3JAX_TEST_XLA_DEFAULTS"):
        return  # a worker inherits the controller's choice
    flags = os.environ.get("XLA_FLAGS", "")
    ours = [f for f in XLA_CPU_FLAGS if f.split("=")[0] not in flags]  # the caller's win
    if ours and not _xla_accepts(" ".join([flags, *ours]).strip()):
        ours = [f for f in ours if _xla_accepts(f"{flags} {f}".strip())]
    if ours:
        os.environ["XLA_FLAGS"] = " ".join([flags, *ours]).strip()


_choose_xla_flags()  # before JAX starts its backend in this process

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)

#: Python's cyclic garbage collector runs less often than by default (the youngest
#: generation after 700 net allocations, the middle one every 10th time, the oldest every
#: 100th): tracing allocates many short-lived objects, and a collection of the oldest
#: generation walks the whole heap of traced and compiled programs that the suite's
#: caches keep, several times a test. Each worker sets this for itself; the library never
#: does (a user's process keeps Python's defaults).
gc.set_threshold(20000, 20, 50)

#: Modules by their share of the suite's time (seconds summed over their tests on the 2-core
#: CPU, with the XLA settings above), longest first. pytest-xdist's
#: ``--dist loadfile`` hands whole modules to its workers in collection order (with
#: ``--no-loadscope-reorder``, set in pyproject.toml; by default it orders them by their
#: number of tests), so the long ones start first and the short ones fill the end, and the
#: workers finish closer together than when ordered by test count.
#: Unlisted modules go last.
_MODULE_SECONDS = {
    "test_engine.py": 196,
    "test_notebooks.py": 100,  # its kernels' CPU time: they run beside the worker
    "test_benchmarks.py": 91,
    "test_quadrotor.py": 63,
    "test_adaptive.py": 61,
    "test_passes_together.py": 52,
    "test_tune.py": 49,
    "test_scalarize.py": 41,
    "test_sweep.py": 38,
    "test_frames.py": 37,
    "test_integrators.py": 29,
    "test_simulate.py": 24,
    "test_so3_grads.py": 21,
    "test_cli.py": 20,
    "test_bad_input.py": 19,
    "test_benchmark_labels.py": 18,
    "test_quadrotor_integral.py": 18,
    "test_sweep_noise.py": 17,
    "test_ambient.py": 17,
    "test_explain.py": 16,
    "test_quadrotor_rotors.py": 15,
    "test_docs_cookbook.py": 15,
    "test_sensor_noise.py": 15,
    "test_scenes_tracking.py": 14,
    "test_docs_own_vehicle.py": 14,
    "test_pass_scalarize.py": 12,
    "test_sweep_outcomes.py": 11,
    "test_sweep_distributed.py": 11,
    "test_sweep_robustness.py": 10,
    "test_rotor_allocation.py": 10,
    "test_so3.py": 10,
    "test_suslov.py": 9,
    "test_pass_hoist.py": 8,
    "test_pass_tiles.py": 7,
    "test_policy.py": 7,
    "test_sweep_params.py": 7,
    "test_jax_gate.py": 7,
    "test_euler.py": 7,
    "test_gust.py": 6,
    "test_jax_state.py": 6,
    "test_pass_frames.py": 5,
    "test_scene_limits.py": 5,
    "test_control.py": 5,
}


def pytest_collection_modifyitems(config, items):
    """Longest modules first (a stable sort: the order within a module is kept)."""
    items.sort(key=lambda item: -_MODULE_SECONDS.get(item.path.name, 0))


def _equations(jaxpr):
    """Every equation of ``jaxpr``, those of its nested jaxprs included (depth first)."""
    from so3jax._engine.passes.scalarize import equations

    return (e for e, _ in equations(jaxpr))


def _count_cuts(jaxpr) -> int:
    from so3jax._engine.passes.cuts import _is_cut

    return sum(
        e.primitive.name == "cond" and _is_cut(e.params["branches"]) for e in _equations(jaxpr)
    )


@pytest.fixture
def equations():
    """``equations(jaxpr)``: every equation of a jaxpr, nested ones included."""
    return _equations


@pytest.fixture
def count_cuts():
    """How many fusion cuts (`_scalarize._is_cut` conditionals) a jaxpr holds, nested ones
    included."""
    return _count_cuts


@pytest.fixture
def engine_policy():
    """``engine_policy(**changes)`` activates the engine's policy with ``changes`` (fields of
    `so3jax._engine.policy.Policy`) for the rest of the test, and returns it."""
    import contextlib

    from so3jax._engine import policy

    with contextlib.ExitStack() as stack:
        yield lambda **changes: stack.enter_context(policy.using(**changes))
