"""The session-tag lint (``.ci/lint_tags.py``): clean on the repository, and it fails on a
tag or a dated measurement planted in a temporary copy of a few of the repository's files.

The planted strings are built at run time, so that this file holds none itself.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / ".ci" / "lint_tags.py"

_spec = importlib.util.spec_from_file_location("lint_tags", SCRIPT)
lint_tags = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(lint_tags)

TAG = "S" + "46"  # a work-session label
DATE = "-".join(["2026", "11", "25"])  # an ISO date
#: Real files of each kind the lint reads: Python, Markdown, a notebook, benchmark output.
COPIED = [
    "so3jax/_engine/passes/frames.py",
    "docs/conventions.md",
    "notebooks/01_so3_in_practice.ipynb",
    "benchmarks/results/stability.json",
]


@pytest.fixture
def copy(tmp_path):
    """A temporary copy of `COPIED` (not a git checkout: the lint walks the folder)."""
    for rel in COPIED:
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / rel, tmp_path / rel)
    return tmp_path


def _run(root: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(SCRIPT), "--root", str(root)], capture_output=True, text=True
    )


def test_the_repository_is_clean():
    findings = lint_tags.lint(ROOT)
    assert not findings, "session tags or dates in the repository:\n" + "\n".join(findings)


def test_the_copy_is_clean_and_a_planted_tag_fails(copy):
    assert _run(copy).returncode == 0, _run(copy).stdout
    path = copy / "so3jax" / "_engine" / "passes" / "frames.py"
    lines = path.read_text(encoding="utf-8").splitlines()
    lines.insert(2, f"The dense rule took about 110 operations a column ({TAG}).")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    result = _run(copy)
    assert result.returncode == 1
    assert "so3jax/_engine/passes/frames.py:3: session tag: The dense rule" in result.stdout


@pytest.mark.parametrize(
    "rel, text",
    [
        ("so3jax/_engine/passes/frames.py", f"# measured on a 2-core CPU ({DATE}): 1.2x faster\n"),
        ("docs/conventions.md", f"\nThe sweep ran at 2e6 body-steps/s ({DATE}).\n"),
    ],
)
def test_a_planted_dated_measurement_fails(copy, rel, text):
    with open(copy / rel, "a", encoding="utf-8") as f:
        f.write(text)
    result = _run(copy)
    assert result.returncode == 1
    assert f"{rel}:" in result.stdout and "dated measurement" in result.stdout


def test_notebook_sources_and_text_outputs_are_read_not_images(copy):
    path = copy / COPIED[2]
    nb = json.loads(path.read_text(encoding="utf-8"))
    code = next(i for i, c in enumerate(nb["cells"]) if c["cell_type"] == "code")
    # Base64 image data may hold an S and two digits after its opening quote: not read.
    nb["cells"][code].setdefault("outputs", []).append(
        {"output_type": "display_data", "metadata": {}, "data": {"image/png": TAG + "AAA="}}
    )
    path.write_text(json.dumps(nb), encoding="utf-8")
    assert lint_tags.lint(copy) == []
    nb["cells"][0]["source"] = ["A markdown cell\n", f"from the run of {TAG}.\n"]
    nb["cells"][code]["outputs"].append({"output_type": "stream", "name": "stdout", "text": TAG})
    path.write_text(json.dumps(nb), encoding="utf-8")
    findings = lint_tags.lint(copy)
    assert [f.split(": ")[0] for f in findings] == [
        f"{COPIED[2]}:cell 1 line 2",
        f"{COPIED[2]}:cell {code + 1} line 1",
    ]


def test_what_is_not_a_tag_or_a_dated_measurement(copy):
    # SO(3), the sphere S^3 and S3, hex and base64 strings, a tag inside a word; a date in
    # benchmark output (its run's record) and on a release heading of the changelog.
    with open(copy / "docs" / "conventions.md", "a", encoding="utf-8") as f:
        f.write(
            "\nSO3 and SO(3); the sphere S3, S^3 and S^{3}; unit quaternions on S_3.\n"
            f"Hashes 9f{TAG}ab and +{TAG}/ and ={TAG}; names like X{TAG} or {TAG}0.\n"
        )
    results = copy / COPIED[3]
    data = json.loads(results.read_text(encoding="utf-8"))
    data["date"] = DATE
    results.write_text(json.dumps(data), encoding="utf-8")
    (copy / "CHANGELOG.md").write_text(f"# Changelog\n\n## [0.1.0] - {DATE}\n", encoding="utf-8")
    assert lint_tags.lint(copy) == []
    # The same date in the changelog's prose is not a release heading.
    with open(copy / "CHANGELOG.md", "a", encoding="utf-8") as f:
        f.write(f"\nMeasured on {DATE}.\n")
    assert lint_tags.lint(copy) == [f"CHANGELOG.md:5: dated measurement: Measured on {DATE}."]


def test_a_tag_in_benchmark_output_fails(copy):
    results = copy / COPIED[3]
    data = json.loads(results.read_text(encoding="utf-8"))
    data["note"] = f"{TAG}, one H100 lease"
    results.write_text(json.dumps(data, indent=1), encoding="utf-8")
    findings = lint_tags.lint(copy, [COPIED[3]])
    assert len(findings) == 1 and findings[0].startswith(f"{COPIED[3]}:")
