"""`benchmarks/report.py`: the figure tables in the docs are the ones the results give.

The check runs on the repository as CI runs it, and on a copy whose results JSON has one
figure changed: the check must then fail and name the stale block, and a rewrite must
make it pass again.
"""

import importlib.util
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "benchmarks" / "report.py"


@pytest.fixture(scope="module")
def report():
    spec = importlib.util.spec_from_file_location("bench_report", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _copy(tmp_path: Path) -> Path:
    """The files `--root` reads: the results' JSON and the three Markdown files."""
    (tmp_path / "benchmarks" / "results").mkdir(parents=True)
    (tmp_path / "docs").mkdir()
    for path in (ROOT / "benchmarks" / "results").glob("*.json"):
        shutil.copy(path, tmp_path / "benchmarks" / "results" / path.name)
    for rel in ("README.md", "benchmarks/README.md", "docs/performance.md"):
        shutil.copy(ROOT / rel, tmp_path / rel)
    return tmp_path


def test_check_passes_on_the_repository(report, capsys):
    assert report.main(["--check"]) == 0, capsys.readouterr().out


def test_every_block_is_placed_and_names_existing_sources(report):
    """Each generated block sits in the docs, and every result file a table names exists."""
    texts = {rel: (ROOT / rel).read_text() for rel in report.FILES}
    placed = {m["name"] for t in texts.values() for m in report.BLOCK.finditer(t)}
    assert placed == set(report.BLOCKS)
    assert "how-fast" in {m["name"] for m in report.BLOCK.finditer(texts["README.md"])}
    named = set()
    for t in texts.values():
        named |= set(re.findall(r"benchmarks/results/([\w.-]+\.json)", t))
        named |= set(re.findall(r"`([\w.-]+\.json)` \|", t))  # the sweep table's column
    assert named
    missing = [n for n in named if not (ROOT / "benchmarks" / "results" / n).is_file()]
    assert not missing


def test_check_fails_on_a_changed_figure_and_a_rewrite_fixes_it(report, tmp_path, capsys):
    root = _copy(tmp_path)
    assert report.main(["--check", "--root", str(root)]) == 0

    # One figure of one result: the 256-run gradient's ratio to its forward pass.
    path = root / "benchmarks" / "results" / "tune.json"
    data = json.loads(path.read_text())
    (row,) = [
        r
        for r in data["rows"]
        if (r["variant"], r["batch"], r["n_steps"]) == ("reverse (default)", 256, 1000)
    ]
    row["time_ratio"] = 9.87
    path.write_text(json.dumps(data))
    capsys.readouterr()

    assert report.main(["--check", "--root", str(root)]) == 1
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert "benchmarks/README.md: stale report blocks: gradients" in lines
    assert "README.md: stale report blocks: how-fast" in lines
    assert "docs/performance.md: stale report blocks: how-fast, gradients" in lines
    assert "+| reverse (default) |" in out and "9.87x" in out  # the diff shows the new row
    # The command line says the same with its exit status.
    cli = subprocess.run(
        [sys.executable, str(SCRIPT), "--check", "--root", str(root)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert cli.returncode == 1 and "gradients" in cli.stdout

    assert report.main(["--root", str(root)]) == 0
    assert "9.87x" in (root / "docs" / "performance.md").read_text()
    assert report.main(["--check", "--root", str(root)]) == 0


def test_a_missing_result_is_not_measured(report, tmp_path, capsys):
    """Without a GPU's tune results, the how-fast gradient row says so instead of a figure."""
    root = _copy(tmp_path)
    for path in (root / "benchmarks" / "results").glob("tune-gpu*.json"):
        path.unlink()
    assert report.main(["--root", str(root)]) == 0
    readme = (root / "README.md").read_text()
    row = next(line for line in readme.splitlines() if line.startswith("| A gradient"))
    assert row.endswith("| not measured (`benchmarks/tune.py` on a GPU) |")


def test_unknown_or_unpaired_markers_are_errors(report, tmp_path, capsys):
    root = _copy(tmp_path)
    page = root / "docs" / "performance.md"
    page.write_text("<!-- report:no-such-table -->\n<!-- /report:no-such-table -->\n")
    assert report.main(["--check", "--root", str(root)]) == 2
    assert "no-such-table" in capsys.readouterr().err
    page.write_text("<!-- report:sweep -->\n")
    assert report.main(["--root", str(root)]) == 2
