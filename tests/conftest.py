"""Test configuration: float64 on for the suite (the library itself never touches it)."""

import os
import subprocess
import sys

os.environ.setdefault("MPLBACKEND", "Agg")

#: XLA's CPU compiler has two code generators for fused kernels: the MLIR "fusion
#: emitters" (its default since 2025) and the older LLVM IR emitters. Measured on this
#: suite's 2-core CPU (2026-11-25), the older ones compile the library's programs 1.2 to
#: 1.6x faster and run them as fast or faster; the suite spends most of its time in XLA's
#: compiler, and took 6:35 against 9:36 with them. The tests therefore run with them
#: (every worker and notebook kernel inherits this process's XLA_FLAGS), unless
#: SO3JAX_TEST_XLA_DEFAULTS=1 asks for XLA's own defaults or a jaxlib no longer knows the
#: flag. Results agree to round-off either way; nothing in the library depends on it.
XLA_CPU_FLAG = "--xla_cpu_use_fusion_emitters=false"


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
    if "fusion_emitters" in flags:
        return  # the caller chose
    candidate = f"{flags} {XLA_CPU_FLAG}".strip()
    if _xla_accepts(candidate):
        os.environ["XLA_FLAGS"] = candidate


_choose_xla_flags()  # before JAX starts its backend in this process

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

#: Modules by their share of the suite's time (seconds on the 2-core CPU, 2026-11-25, with
#: the older emitters above), longest first. pytest-xdist's ``--dist loadfile`` hands whole
#: modules to its workers in collection order (with ``--no-loadscope-reorder``, set in
#: pyproject.toml; by default it orders them by their number of tests), so the long ones
#: start first and the short ones fill the end: the workers finished 7 s apart (5:27 in
#: all; ordered by test count, 25 to 39 s apart). Unlisted modules go last.
_MODULE_SECONDS = {
    "test_benchmarks.py": 83,
    "test_quadrotor.py": 75,
    "test_engine.py": 61,
    "test_notebooks.py": 58,
    "test_adaptive.py": 47,
    "test_sweep.py": 39,
    "test_scalarize.py": 37,
    "test_tune.py": 31,
    "test_integrators.py": 30,
    "test_simulate.py": 27,
    "test_so3_grads.py": 21,
    "test_cli.py": 19,
    "test_scenes_tracking.py": 18,
    "test_ambient.py": 17,
    "test_suslov.py": 14,
    "test_sweep_outcomes.py": 13,
    "test_sweep_params.py": 11,
    "test_so3.py": 10,
    "test_sweep_distributed.py": 9,
}


def pytest_collection_modifyitems(config, items):
    """Longest modules first (a stable sort: the order within a module is kept)."""
    items.sort(key=lambda item: -_MODULE_SECONDS.get(item.path.name, 0))
