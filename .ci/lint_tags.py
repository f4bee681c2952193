#!/usr/bin/env python3
"""Fail on work-session labels and dated measurements in the repository's text.

The repository speaks of the project, not of its history: a docstring states the
contract, a figure comes from ``benchmarks/results/`` through a generated table, and
what was tried when is git's to keep. This lint enforces two rules.

1. **Session tags.** A capital ``S`` followed by two digits (and an optional lower-case
   letter) as a word. The pattern is the one of the before-stop hook,
   ``(^|[^A-Za-z0-9_+/=])S[0-9]{2}[a-z]?\\b``: a tag preceded by a letter, digit,
   underscore or a base64 character (``+ / =``) is not one, so ``SO3``, ``S3`` (the
   sphere), ``S^3``, hex strings and base64 image data never match. Checked in every
   text file, benchmark output (``benchmarks/results/*.json``) included.
2. **Dated measurements.** An ISO date (year-month-day) in Python source (docstrings
   and comments are where a dated figure hides) and in prose: Markdown files and the
   sources of notebooks. Benchmark output (JSON) records its date on purpose and is
   not checked for dates, nor is ``CHANGELOG.md``, whose release headings carry dates
   (Keep a Changelog).

What is scanned: the files git knows (``git ls-files --cached --others
--exclude-standard`` in the root: tracked files and new ones not ignored), or, outside a
git checkout, every file under the root but dot-folders, virtual environments and build
output; or the files named on the command line. Binary files (a NUL byte, or not UTF-8)
are skipped. A notebook is read as JSON: its markdown and code sources and its text
outputs are checked, not its images.

An exception is an `ALLOWED` entry: a path pattern, the rule, a regular expression the
offending line matches, and the reason.

Usage: ``python .ci/lint_tags.py [--root DIR] [FILE ...]``. Exit status 0 when clean,
1 with one ``path:line: rule: text`` line per finding.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import os
import re
import subprocess
import sys
from pathlib import Path

#: A work-session label (the before-stop hook's pattern).
TAG = re.compile(r"(^|[^A-Za-z0-9_+/=])S[0-9]{2}[a-z]?\b")
#: An ISO calendar date.
DATE = re.compile(
    r"(?<![0-9])(?:19|20)[0-9]{2}-(?:0[1-9]|1[0-2])-(?:0[1-9]|[12][0-9]|3[01])(?![0-9])"
)

#: Suffixes whose text is prose or code, where a date is a dated measurement.
DATED_SUFFIXES = (".py", ".md", ".ipynb")

#: Folders never walked outside a git checkout.
SKIP_DIRS = {"__pycache__", "site", "build", "dist", "node_modules", "so3jax-output", "out"}

#: Exceptions: ``(path glob, rule, line regex, reason)``. ``rule`` is ``"tag"`` or
#: ``"date"``; a finding is allowed when its path matches the glob and its line the regex.
ALLOWED: list[tuple[str, str, str, str]] = [
    (
        "CHANGELOG.md",
        "date",
        r"^## \[",
        "Keep a Changelog: each release heading carries its date",
    ),
]


def _allowed(path: str, rule: str, line: str) -> bool:
    return any(
        fnmatch.fnmatch(path, glob) and rule == r and re.search(pattern, line)
        for glob, r, pattern, _ in ALLOWED
    )


def repository_files(root: Path) -> list[str]:
    """Paths (relative to ``root``, POSIX) of the files to scan under ``root``."""
    try:
        out = subprocess.run(
            ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
            cwd=root,
            capture_output=True,
            check=True,
        ).stdout
        if (root / ".git").exists():
            return sorted({p for p in out.decode().split("\0") if p})
    except (OSError, subprocess.CalledProcessError):
        pass
    found = []
    for folder, dirs, files in os.walk(root):
        dirs[:] = [
            d
            for d in dirs
            if not d.startswith(".") or d == ".ci"
            if d not in SKIP_DIRS and not d.endswith(("venv", ".egg-info"))
        ]
        for f in files:
            found.append((Path(folder) / f).relative_to(root).as_posix())
    return sorted(found)


def _text(path: Path) -> str | None:
    """The file's text, or ``None`` for a binary file (a NUL byte, or not UTF-8)."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    if b"\0" in data:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def _notebook_lines(text: str):
    """``(line, text)`` for every line of a notebook's sources and text outputs; the
    line number is the cell's (1-based) and the line's within it, as ``cell N``."""
    nb = json.loads(text)
    for i, cell in enumerate(nb.get("cells", []), start=1):
        chunks = [cell.get("source", "")]
        for output in cell.get("outputs", []):
            chunks.append(output.get("text", ""))
            data = output.get("data", {})
            for kind in ("text/plain", "text/markdown", "text/html"):
                chunks.append(data.get(kind, ""))
        for chunk in chunks:
            body = "".join(chunk) if isinstance(chunk, list) else chunk
            for k, line in enumerate(body.splitlines(), start=1):
                yield f"cell {i} line {k}", line


def check_file(root: Path, rel: str) -> list[str]:
    """Findings in ``root / rel``, one ``path:where: rule: line`` string each."""
    text = _text(root / rel)
    if text is None:
        return []
    if rel.endswith(".ipynb"):
        try:
            lines = list(_notebook_lines(text))
        except (ValueError, AttributeError):  # not a notebook after all: read as text
            lines = [(str(k), s) for k, s in enumerate(text.splitlines(), start=1)]
    else:
        lines = [(str(k), s) for k, s in enumerate(text.splitlines(), start=1)]
    dates = rel.endswith(DATED_SUFFIXES)
    findings = []
    for where, line in lines:
        for rule, pattern, on in (("tag", TAG, True), ("date", DATE, dates)):
            if on and pattern.search(line) and not _allowed(rel, rule, line):
                what = "session tag" if rule == "tag" else "dated measurement"
                findings.append(f"{rel}:{where}: {what}: {line.strip()[:160]}")
    return findings


def lint(root: Path, files: list[str] | None = None) -> list[str]:
    """Every finding under ``root`` (in ``files`` if given, paths relative to ``root``)."""
    root = Path(root)
    paths = files if files else repository_files(root)
    return [f for rel in paths for f in check_file(root, rel)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1])
    parser.add_argument("files", nargs="*", help="paths relative to --root (default: all)")
    args = parser.parse_args(argv)
    findings = lint(args.root, args.files or None)
    for f in findings:
        print(f)
    if findings:
        print(
            f"{len(findings)} finding(s): state the fact without its history (no session "
            "labels, no dates); figures belong in benchmarks/results/ and generated tables.",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
