"""Test configuration: float64 on for the suite (the library itself never touches it)."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

#: Modules by their share of the suite's time (seconds on the 2-core CPU, 2026-11-25),
#: longest first. pytest-xdist's ``--dist loadfile`` hands whole modules to its workers
#: in collection order (with ``--no-loadscope-reorder``, set in pyproject.toml; by default
#: it orders them by their number of tests), so the long ones start first and the short
#: ones fill the end (ordered by test count, the workers finished 25 to 39 s apart).
#: Unlisted modules go last.
_MODULE_SECONDS = {
    "test_engine.py": 143,
    "test_benchmarks.py": 129,
    "test_quadrotor.py": 123,
    "test_notebooks.py": 100,
    "test_adaptive.py": 83,
    "test_scalarize.py": 75,
    "test_sweep.py": 70,
    "test_tune.py": 67,
    "test_simulate.py": 52,
    "test_integrators.py": 51,
    "test_sweep_outcomes.py": 38,
    "test_so3_grads.py": 37,
    "test_ambient.py": 35,
    "test_scenes_tracking.py": 35,
    "test_cli.py": 29,
    "test_so3.py": 22,
    "test_suslov.py": 22,
    "test_sweep_params.py": 20,
    "test_sweep_distributed.py": 18,
}


def pytest_collection_modifyitems(config, items):
    """Longest modules first (a stable sort: the order within a module is kept)."""
    items.sort(key=lambda item: -_MODULE_SECONDS.get(item.path.name, 0))
