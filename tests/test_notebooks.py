"""The notebooks in ``notebooks/`` run from top to bottom without an error.

Each notebook is executed in a fresh Jupyter kernel of the interpreter that
runs pytest (so the notebooks use whatever environment the suite uses), with
``SO3JAX_NB_QUICK=1`` (smaller runs), the working tree first on the path and
a scratch folder as the working directory. The notebooks check their own
results with ``assert`` cells, so a failure here is either a crash or a
failed check, reported with the cell's traceback. The notebooks are executed
two at a time (most of their time is single-threaded compilation), in scratch
copies: nothing is written back.

The notebooks are stored *with* outputs, written by ``notebooks/execute.py``
(full mode). Each records a hash of its code cells and of the library's
sources; a test checks that the hash is current, so the stored outputs come
from the current code.
"""

from __future__ import annotations

import functools
import gc
import importlib.util
import json
import os
import re
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
IDS = [p.stem for p in NOTEBOOKS]
CELL_TIMEOUT = 600  # seconds per cell: generous, for a loaded 2-core machine
KERNEL = "so3jax-tests"


def test_there_are_notebooks():
    assert len(NOTEBOOKS) >= 3, f"expected the notebooks in {ROOT / 'notebooks'}"


def _load_execute_script():
    spec = importlib.util.spec_from_file_location("_nb_execute", ROOT / "notebooks" / "execute.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


RERUN = "run `python notebooks/execute.py` and commit the notebooks"
# A cell that prints or shows a figure must have stored outputs.
SHOWS_SOMETHING = re.compile(r"\b(print|display)\(|plt\.show\(|^\s*fig\s*$", re.MULTILINE)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=IDS)
def test_notebook_outputs_are_current(path):
    """The stored outputs come from one run of the current cells on the current library."""
    execute = _load_execute_script()
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    stored = execute.stored_hash(nb)
    assert stored is not None, f"{path.name} has no stored outputs hash; {RERUN}"
    assert stored == execute.source_hash(nb), (
        f"{path.name}: its outputs are stale (its code cells or so3jax/ changed since it "
        f"was executed); {RERUN}"
    )
    code = [c for c in nb.cells if c.cell_type == "code" and c.source.strip()]
    for n, cell in enumerate(code, start=1):
        where = f"{path.name}, code cell {n}"
        # Counts 1, 2, 3, ...: every cell ran, in order, in one kernel.
        assert cell.execution_count == n, f"{where} was not executed in order; {RERUN}"
        errors = [o for o in cell.outputs if o.output_type == "error"]
        assert not errors, f"{where} stored an error: {errors[0].get('ename')}"
        if SHOWS_SOMETHING.search(cell.source):
            assert cell.outputs, f"{where} prints or shows a figure but has no outputs; {RERUN}"


def _write_kernel_spec(folder: Path) -> None:
    """A kernel spec that starts this very interpreter, whichever virtualenv it is.

    (A user-wide ``python3`` spec could point at another Python.) The kernel runs
    Python's garbage collector as seldom as the suite's workers do (``conftest.py``),
    and otherwise starts as ``python -m ipykernel_launcher`` does.
    """
    spec = folder / "kernels" / KERNEL
    spec.mkdir(parents=True)
    start = (
        f"import gc; gc.set_threshold{gc.get_threshold()}; "
        "from ipykernel import kernelapp; kernelapp.launch_new_instance()"
    )
    argv = [sys.executable, "-c", start, "-f", "{connection_file}"]
    kernel = {"argv": argv, "display_name": "so3jax tests", "language": "python"}
    (spec / "kernel.json").write_text(json.dumps(kernel))


def _kernel_env(scratch: Path) -> dict[str, str]:
    env = {
        "SO3JAX_NB_QUICK": "1",
        # Inline figures, as for a reader (conftest selects Agg for this process,
        # which the kernel would otherwise inherit).
        "MPLBACKEND": "module://matplotlib_inline.backend_inline",
        "MPLCONFIGDIR": str(scratch / "mplconfig"),
        "JUPYTER_PATH": str(scratch / "jupyter"),
        # Test the working tree, even where so3jax is not installed in editable mode.
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    return env


@functools.cache
def _without_heartbeat():
    """A kernel client class that starts no heartbeat channel.

    The kernel is a local process that its manager polls for liveness, so the heartbeat
    adds nothing here. Stopping jupyter_client's heartbeat thread at a kernel's cleanup
    can hang (its thread stayed in an ``await`` on the heartbeat socket, and
    ``HBChannel.stop`` joins it without a timeout), which hung a whole CI run.
    """
    from jupyter_client.asynchronous import AsyncKernelClient

    class Client(AsyncKernelClient):
        def start_channels(self, *args, **kwargs):
            kwargs["hb"] = False
            return super().start_channels(*args, **kwargs)

    return Client


def _execute(path: Path, cwd: Path) -> list[str]:
    """Run a notebook in a fresh kernel; return its errors (empty: it ran through)."""
    from jupyter_client.manager import AsyncKernelManager

    nb = nbformat.read(path, as_version=4)
    cwd.mkdir(parents=True)
    km = AsyncKernelManager(kernel_name=KERNEL)
    km.client_factory = _without_heartbeat()
    client = nbclient.NotebookClient(
        nb,
        km=km,
        timeout=CELL_TIMEOUT,
        kernel_name=KERNEL,
        # A scratch working directory: anything a notebook writes stays out of the repo.
        resources={"metadata": {"path": str(cwd)}},
    )
    client.owns_km = True  # so it shuts the kernel down and stops its channels at the end
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as e:
        return [re.sub(r"\x1b\[[0-9;]*m", "", str(e))]  # without the terminal colours
    return [
        f"cell {i}: {o['ename']}: {o['evalue']}"
        for i, cell in enumerate(nb.cells)
        for o in cell.get("outputs", [])
        if o.get("output_type") == "error"
    ]


@pytest.fixture(scope="module")
def executions(request, tmp_path_factory):
    """Start every selected notebook, two at a time; map each path to its future."""
    selected = {
        item.callspec.params["path"]
        for item in request.session.items
        if getattr(item, "originalname", None) == "test_notebook_runs"
    }
    scratch = tmp_path_factory.mktemp("notebooks")
    _write_kernel_spec(scratch / "jupyter")
    with pytest.MonkeyPatch.context() as mp:
        # Kernels inherit this process's environment when they start.
        for key, value in _kernel_env(scratch).items():
            mp.setenv(key, value)
        workers = max(1, min(2, os.cpu_count() or 1))
        with ThreadPoolExecutor(max_workers=workers) as pool:
            yield {
                p: pool.submit(_execute, p, scratch / p.stem) for p in NOTEBOOKS if p in selected
            }


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=IDS)
def test_notebook_runs(path, executions):
    errors = executions[path].result()
    if errors:
        pytest.fail(f"{path.name} failed:\n" + "\n".join(errors), pytrace=False)
