"""mkdocs hook: serve files that live outside docs/ without keeping copies in git.

- ``notebooks/*.ipynb`` become pages (rendered by mkdocs-jupyter from the
  outputs stored in them; see ``notebooks/execute.py``);
- ``benchmarks/results/*.png`` become images (the ``-quick`` smoke-run
  figures are left out).

Both keep their repository paths in the site, so a page links to
``notebooks/02_integrators.ipynb`` or ``benchmarks/results/stability.png``
and always shows the committed notebooks and the latest benchmark figures.
"""

from __future__ import annotations

from pathlib import Path

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[1]
SOURCES = [("notebooks", "*.ipynb"), ("benchmarks/results", "*.png")]


@event_priority(100)  # before mkdocs-jupyter turns .ipynb files into pages
def on_files(files, config):
    for folder, pattern in SOURCES:
        for path in sorted((ROOT / folder).glob(pattern)):
            if path.stem.endswith("-quick"):
                continue
            uri = path.relative_to(ROOT).as_posix()
            files.append(File(uri, str(ROOT), config["site_dir"], config["use_directory_urls"]))
    return files
