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


def _ablation_result(backend: str, slowdowns: dict, compile_rounds: int) -> dict:
    """An ablation JSON of one workload: ``slowdowns`` maps a pass to its run-time ratio
    when off (1.0: the same program); every compilation with a pass off takes 1.5x."""
    rows = []
    for config, ratio in [("all passes", 1.0), *((f"no {p}", s) for p, s in slowdowns.items())]:
        t, c = 0.01 * ratio, [1.0 if config == "all passes" else 1.5] * compile_rounds
        same = config == "all passes" or ratio == 1.0
        rows.append(
            {
                "workload": "run",
                "config": config,
                "run_s": t,
                "rounds": [t, t * 1.01],
                "compile_s": min(c),
                "compile_s_rounds": c,
                "same_program_as_base": same,
            }
        )
    env = {
        "backend": backend,
        "device_kind": "NVIDIA H200" if backend == "gpu" else "cpu",
        "cpu_count": 2,
        "jax": "0.11.2",
    }
    return {
        "env": env,
        "dtype": "float64",
        "method": "RKMK4",
        "compile_rounds": compile_rounds,
        "passes": sorted(slowdowns),
        "configs": {"all passes": {}, **{f"no {p}": {} for p in slowdowns}},
        "workloads": {"run": {"label": "one run"}},
        "rows": rows,
    }


def test_a_pass_is_removed_only_where_it_buys_nothing_on_every_machine(report, tmp_path):
    """The ablation's removal rule over the CPU's and a GPU's results: `hoist` buys 3x on the
    CPU alone and stays; `tiles` buys nothing on either and is named. A compile time measured
    once (the GPU's) is not a gain: its noise is not measured; measured three times and
    slower in every round (the CPU's), it is."""
    (tmp_path / "ablation.json").write_text(
        json.dumps(_ablation_result("cpu", {"hoist": 3.0, "tiles": 1.0}, compile_rounds=3))
    )
    gpu = _ablation_result("gpu", {"hoist": 1.0, "tiles": 1.0}, compile_rounds=1)
    (tmp_path / "ablation-gpu-h200.json").write_text(json.dumps(gpu))
    text = report.ablation(report.Results(tmp_path))
    cpu_part, gpu_part = text.split("On NVIDIA H200 (JAX 0.11.2):")
    assert "candidate for removal on this machine: none." in cpu_part  # compile 1.5x, 3 rounds
    assert "candidate for removal on this machine: `hoist`, `tiles`." in gpu_part
    assert "Slower to compile with a pass off (compile time): none." in gpu_part
    assert text.rstrip().endswith("(CPU, 2 cores; NVIDIA H200): none.")  # tiles's CPU compile
    (tmp_path / "ablation.json").write_text(
        json.dumps(_ablation_result("cpu", {"hoist": 3.0, "tiles": 1.0}, compile_rounds=1))
    )
    text = report.ablation(report.Results(tmp_path))
    assert text.rstrip().endswith("(CPU, 2 cores; NVIDIA H200): `tiles`.")
