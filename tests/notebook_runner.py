"""Run one notebook in a fresh Jupyter kernel: ``python notebook_runner.py NOTEBOOK CWD``.

``test_notebooks.py`` starts one such process per notebook. It prints one line,
``RESULT <JSON list of errors>`` (empty: the notebook ran through), as soon as the last
code cell has run or a cell has failed, before the kernel is shut down. The caller takes
that line and stops a process whose cleanup does not end; a kernel whose parent is gone
exits by itself (ipykernel's parent poller).

The kernel is the ``so3jax-tests`` spec the caller writes (``JUPYTER_PATH``), started
with the caller's environment, and runs in ``CWD``. Nothing is written back to
``NOTEBOOK``.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import nbclient
import nbformat
from jupyter_client.asynchronous import AsyncKernelClient
from jupyter_client.manager import AsyncKernelManager

KERNEL = "so3jax-tests"
CELL_TIMEOUT = 600  # seconds per cell: generous, for a loaded 2-core machine


class _WithoutHeartbeat(AsyncKernelClient):
    """A kernel client that starts no heartbeat channel.

    The kernel is a local process that its manager polls for liveness, so the heartbeat
    adds nothing here. Stopping jupyter_client's heartbeat thread at a kernel's cleanup
    can hang (``HBChannel.stop`` joins its thread without a timeout).
    """

    def start_channels(self, *args, **kwargs):
        kwargs["hb"] = False
        return super().start_channels(*args, **kwargs)


def _report(errors: list[str], sent: list) -> None:
    if not sent:
        sent.append(True)
        print("RESULT " + json.dumps(errors), flush=True)


def _plain(error) -> str:
    """An error's message without the terminal's colour codes."""
    return re.sub(r"\x1b\[[0-9;]*m", "", str(error))


def _errors(nb) -> list[str]:
    return [
        f"cell {i}: {o['ename']}: {o['evalue']}"
        for i, cell in enumerate(nb.cells)
        for o in cell.get("outputs", [])
        if o.get("output_type") == "error"
    ]


def main(path: Path, cwd: Path) -> None:
    nb = nbformat.read(path, as_version=4)
    cwd.mkdir(parents=True, exist_ok=True)
    code = [i for i, cell in enumerate(nb.cells) if cell.cell_type == "code"]
    sent: list = []

    def executed(cell, cell_index, execute_reply):
        content = (execute_reply or {}).get("content", {})
        if content.get("status") == "error":  # reported as nbclient raises it, with its source
            _report(
                [_plain(nbclient.exceptions.CellExecutionError.from_cell_and_msg(cell, content))],
                sent,
            )
        elif code and cell_index == code[-1]:
            _report(_errors(nb), sent)

    km = AsyncKernelManager(kernel_name=KERNEL)
    km.client_factory = _WithoutHeartbeat
    client = nbclient.NotebookClient(
        nb,
        km=km,
        timeout=CELL_TIMEOUT,
        kernel_name=KERNEL,
        resources={"metadata": {"path": str(cwd)}},
        on_cell_executed=executed,
    )
    client.owns_km = True  # so it shuts the kernel down and stops its channels at the end
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as e:
        _report([_plain(e)], sent)
    except Exception as e:  # a dead kernel, a timeout: the notebook did not run through
        _report([f"{type(e).__name__}: {e}"], sent)
    _report(_errors(nb), sent)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
