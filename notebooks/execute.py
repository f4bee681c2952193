"""Re-run the notebooks in place, so that they are stored with current outputs.

    python notebooks/execute.py                  # every notebook in notebooks/
    python notebooks/execute.py 02_integrators   # only some (names or paths)
    python notebooks/execute.py --check          # only say which ones are stale

The notebooks are committed *with* their outputs (so a repository page and the
documentation site show the figures), and those outputs must come from the
current code. So each notebook records, in ``metadata["so3jax"]["source_hash"]``,
a SHA-256 over

1. the sources of its code cells, in order, and
2. the contents of every ``so3jax/**/*.py`` file, sorted by path,

and ``tests/test_notebooks.py`` fails when the stored hash differs from the
hash of the current cells and library. The rule that follows: **after changing
a code cell or anything under so3jax/, run this script and commit the
notebooks with the change.** Editing markdown cells needs no re-run.

Each notebook runs top to bottom in a fresh kernel of this very interpreter
(full mode: ``SO3JAX_NB_QUICK`` is removed from its environment), with the
working tree first on the path and a scratch folder as working directory.
A notebook that raises is not written back; the script exits with status 1.
Volatile bits (execution timings, widget state, the Python version) are
stripped so that a re-run changes only what the code changed.
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import json
import os
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK_DIR = ROOT / "notebooks"
LIBRARY_DIR = ROOT / "so3jax"
KERNEL = "so3jax-notebooks"
CELL_TIMEOUT = 1800  # seconds per cell (full mode on a loaded 2-core machine)
# Kept from the kernel's language_info; its version would change with every Python.
LANGUAGE_INFO_KEYS = ("name", "codemirror_mode", "file_extension", "mimetype", "pygments_lexer")


def library_files(root: Path = ROOT) -> list[Path]:
    """Every ``so3jax/**/*.py`` file under ``root``, sorted by path."""
    lib = root / "so3jax"
    return sorted(lib.rglob("*.py"), key=lambda p: p.relative_to(root).as_posix())


def source_hash(nb, root: Path = ROOT) -> str:
    """SHA-256 (hex) over the notebook's code cells and the library's sources.

    Every piece goes in with its length in front, so no two different inputs
    concatenate to the same bytes; line endings are normalised to ``\\n``.
    """
    h = hashlib.sha256()

    def put(tag: str, text: str) -> None:
        data = text.replace("\r\n", "\n").encode()
        h.update(f"{tag} {len(data)}\n".encode())
        h.update(data)

    for cell in nb.cells:
        if cell.cell_type == "code":
            put("cell", cell.source)
    for path in library_files(root):
        put("file", path.relative_to(root).as_posix())
        put("text", path.read_text(encoding="utf-8"))
    return h.hexdigest()


def stored_hash(nb) -> str | None:
    return nb.metadata.get("so3jax", {}).get("source_hash")


def _kernel_env(scratch: Path) -> dict[str, str]:
    env = dict(os.environ)
    env.pop("SO3JAX_NB_QUICK", None)  # full mode
    env.update(
        {
            # Inline figures, as for a reader, whatever backend this shell selects.
            "MPLBACKEND": "module://matplotlib_inline.backend_inline",
            "MPLCONFIGDIR": str(scratch / "mplconfig"),
            "JUPYTER_PATH": str(scratch / "jupyter"),
            # The working tree, even where so3jax is not installed in editable mode.
            "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")])),
        }
    )
    return env


def _write_kernel_spec(folder: Path) -> None:
    """A kernel spec that starts this interpreter (a user-wide spec may be another Python)."""
    spec = folder / "kernels" / KERNEL
    spec.mkdir(parents=True)
    argv = [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"]
    kernel = {"argv": argv, "display_name": "so3jax notebooks", "language": "python"}
    (spec / "kernel.json").write_text(json.dumps(kernel))


def _clean(nb, original_metadata: dict) -> None:
    """Strip what changes from run to run without the code changing."""
    meta = copy.deepcopy(original_metadata)
    meta.pop("widgets", None)
    info = nb.metadata.get("language_info", {})
    meta["language_info"] = {k: info[k] for k in LANGUAGE_INFO_KEYS if k in info}
    nb.metadata = meta
    for cell in nb.cells:
        cell.metadata.pop("execution", None)  # timestamps
        cell.metadata.pop("ExecuteTime", None)
        if cell.cell_type != "code":
            continue
        merged = []  # consecutive prints to one stream: one output, as Jupyter shows them
        for out in cell.outputs:
            last = merged[-1] if merged else None
            if out.output_type == "stream" and last and last.get("name") == out.name:
                last.text += out.text
            else:
                merged.append(out)
        cell.outputs = merged
        for out in cell.outputs:
            # Widget views (tqdm.notebook) point at state that is not stored;
            # their text/plain fallback renders anywhere.
            data = out.get("data", {})
            if "application/vnd.jupyter.widget-view+json" in data:
                data.pop("application/vnd.jupyter.widget-view+json")


def execute(path: Path, scratch: Path) -> tuple[Path, float, str | None]:
    """Run one notebook in place; return (path, seconds, error or None)."""
    import nbclient
    import nbformat

    nb = nbformat.read(path, as_version=4)
    original_metadata = copy.deepcopy(dict(nb.metadata))
    cwd = scratch / path.stem
    cwd.mkdir(parents=True, exist_ok=True)
    client = nbclient.NotebookClient(
        nb,
        timeout=CELL_TIMEOUT,
        kernel_name=KERNEL,
        record_timing=False,
        resources={"metadata": {"path": str(cwd)}},
    )
    start = time.perf_counter()
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as e:
        return path, time.perf_counter() - start, str(e)
    seconds = time.perf_counter() - start
    _clean(nb, original_metadata)
    nb.metadata.setdefault("so3jax", {})["source_hash"] = source_hash(nb)
    nbformat.validate(nb)
    nbformat.write(nb, path)
    return path, seconds, None


def _resolve(names: list[str]) -> list[Path]:
    if not names:
        return sorted(NOTEBOOK_DIR.glob("*.ipynb"))
    paths = []
    for name in names:
        p = Path(name)
        if not p.exists():
            p = NOTEBOOK_DIR / (name if name.endswith(".ipynb") else name + ".ipynb")
        if not p.exists():
            raise SystemExit(f"no notebook {name!r} (looked in {NOTEBOOK_DIR})")
        paths.append(p.resolve())
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("notebooks", nargs="*", help="names or paths (default: all)")
    parser.add_argument("--check", action="store_true", help="only report stale notebooks")
    parser.add_argument("--jobs", type=int, default=1, help="notebooks run at once (default 1)")
    args = parser.parse_args(argv)
    paths = _resolve(args.notebooks)

    if args.check:
        import nbformat

        notebooks = {p: nbformat.read(p, as_version=4) for p in paths}
        stale = [p for p, nb in notebooks.items() if stored_hash(nb) != source_hash(nb)]
        for p in stale:
            print(f"stale: {p.name}")
        print(f"{len(paths) - len(stale)} of {len(paths)} notebooks current")
        return 1 if stale else 0

    failed = False
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="so3jax-nb-") as tmp:
        scratch = Path(tmp)
        _write_kernel_spec(scratch / "jupyter")
        env = _kernel_env(scratch)
        saved = dict(os.environ)
        os.environ.clear()
        os.environ.update(env)  # kernels inherit this process's environment
        try:
            with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
                for path, seconds, error in pool.map(lambda p: execute(p, scratch), paths):
                    if error is None:
                        print(f"{path.name}: {seconds:.0f} s, written", flush=True)
                    else:
                        failed = True
                        print(f"{path.name}: FAILED after {seconds:.0f} s, not written\n{error}")
        finally:
            os.environ.clear()
            os.environ.update(saved)
    print(f"total {time.perf_counter() - start:.0f} s")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
