"""The notebooks in ``notebooks/`` run from top to bottom without an error.

Each notebook is executed in a fresh Jupyter kernel of the interpreter that
runs pytest (so the notebooks use whatever environment the suite uses), with
``SO3JAX_NB_QUICK=1`` (smaller runs), the working tree first on the path and
a scratch folder as the working directory. The notebooks check their own
results with ``assert`` cells, so a failure here is either a crash or a
failed check, reported with the cell's traceback. The notebooks are executed
two at a time (most of their time is single-threaded compilation), each by a
process of its own (``notebook_runner.py``) whose result is taken as soon as it
reports it, so that no kernel's shutdown can hold up the suite; nothing is
written back.

The notebooks are stored *with* outputs, written by ``notebooks/execute.py``
(full mode). Each records a hash of its code cells and of the library's
sources; a test checks that the hash is current, so the stored outputs come
from the current code.
"""

from __future__ import annotations

import gc
import importlib.util
import json
import os
import queue
import re
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
IDS = [p.stem for p in NOTEBOOKS]
KERNEL = "so3jax-tests"  # the spec `notebook_runner` starts


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


#: The most one notebook may take, its kernel's start and shutdown included (a quick run
#: takes well under a minute; a loaded machine several times that).
NOTEBOOK_TIMEOUT = 1200
#: How long a notebook's process may take to shut its kernel down once it has reported.
CLEANUP_TIMEOUT = 60
RUNNER = Path(__file__).resolve().parent / "notebook_runner.py"


def _execute(path: Path, cwd: Path) -> list[str]:
    """Run a notebook in a fresh kernel (`notebook_runner`, a process of its own); return its
    errors (empty: it ran through).

    The result is taken as soon as the process reports it: a process whose kernel cleanup
    does not end within `CLEANUP_TIMEOUT` is stopped, and one that reports nothing within
    `NOTEBOOK_TIMEOUT` fails the notebook; neither holds up the suite.
    """
    log = cwd.parent / f"{path.stem}.stderr"
    with open(log, "w") as err:
        proc = subprocess.Popen(
            [sys.executable, str(RUNNER), str(path), str(cwd)],
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
        )
        lines: queue.Queue = queue.Queue()
        threading.Thread(target=lambda: [lines.put(x) for x in proc.stdout], daemon=True).start()
        deadline = time.monotonic() + NOTEBOOK_TIMEOUT
        result = None
        while result is None and time.monotonic() < deadline:
            try:
                line = lines.get(timeout=5.0)
            except queue.Empty:
                if proc.poll() is not None and lines.empty():
                    break  # exited without a result
                continue
            if line.startswith("RESULT "):
                result = json.loads(line[len("RESULT ") :])
        try:
            proc.wait(timeout=CLEANUP_TIMEOUT if result is not None else 0.1)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    if result is not None:
        return result
    return [f"{path.name}: no result within {NOTEBOOK_TIMEOUT} s:\n{log.read_text()[-3000:]}"]


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


def test_a_failing_cell_fails_the_notebook(tmp_path, monkeypatch):
    """A notebook whose check fails is reported with the failing cell, through the same
    runner and kernel as the notebooks above."""
    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_code_cell("x = 1"), nbformat.v4.new_code_cell("assert x == 2")]
    path = tmp_path / "failing.ipynb"
    nbformat.write(nb, path)
    _write_kernel_spec(tmp_path / "jupyter")
    for key, value in _kernel_env(tmp_path).items():
        monkeypatch.setenv(key, value)
    (errors,) = _execute(path, tmp_path / "failing")
    assert "AssertionError" in errors and "assert x == 2" in errors


def _fake_runner(folder: Path, body: str) -> Path:
    script = folder / "runner.py"
    script.write_text("import sys, time\n" + body)
    return script


def test_a_process_that_reports_and_hangs_is_stopped(tmp_path, monkeypatch):
    """A result reported before a kernel's shutdown hangs counts, and the process is
    stopped after `CLEANUP_TIMEOUT`."""
    body = "print('RESULT []', flush=True)\ntime.sleep(600)\n"
    monkeypatch.setattr(sys.modules[__name__], "RUNNER", _fake_runner(tmp_path, body))
    monkeypatch.setattr(sys.modules[__name__], "CLEANUP_TIMEOUT", 1)
    start = time.monotonic()
    assert _execute(tmp_path / "any.ipynb", tmp_path / "any") == []
    assert time.monotonic() - start < 30


def test_a_process_that_never_reports_fails_the_notebook(tmp_path, monkeypatch):
    """No result within `NOTEBOOK_TIMEOUT`: the notebook fails with the process's stderr,
    and the process is stopped."""
    body = "print('kernel started', file=sys.stderr, flush=True)\ntime.sleep(600)\n"
    monkeypatch.setattr(sys.modules[__name__], "RUNNER", _fake_runner(tmp_path, body))
    monkeypatch.setattr(sys.modules[__name__], "NOTEBOOK_TIMEOUT", 2)
    start = time.monotonic()
    (error,) = _execute(tmp_path / "any.ipynb", tmp_path / "any")
    assert "no result within 2 s" in error and "kernel started" in error
    assert time.monotonic() - start < 30
