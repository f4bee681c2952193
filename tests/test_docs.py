"""The documentation site covers the public API and every notebook.

The API reference (``docs/api/*.md``) is built by mkdocstrings from ``:::
so3jax.NAME`` lines; these tests read those lines (they do not run mkdocs,
which CI does with ``mkdocs build --strict``). A new public name in
``so3jax`` or ``so3jax.scenes`` fails here until it is in ``__all__`` and has
an entry on one of the API pages.
"""

from __future__ import annotations

import re
import types
from pathlib import Path

import so3jax
import so3jax.plot  # noqa: F401  (documented on docs/api/plot.md)
import so3jax.scenes

ROOT = Path(__file__).resolve().parents[1]
API_PAGES = sorted((ROOT / "docs" / "api").glob("*.md"))
DIRECTIVE = re.compile(r"^:::\s+(\S+)\s*$", re.MULTILINE)


def public_names(module: types.ModuleType) -> set[str]:
    """Names a user reaches as ``module.NAME``: no underscore, no submodule, no version."""
    return {
        name
        for name in dir(module)
        if not name.startswith("_")
        and name != "__version__"
        and not isinstance(getattr(module, name), types.ModuleType)
    }


def documented() -> set[str]:
    """Every object named by a ``::: path`` line of the API pages."""
    return {m for page in API_PAGES for m in DIRECTIVE.findall(page.read_text(encoding="utf-8"))}


def test_all_lists_exactly_the_public_names():
    names = so3jax.__all__
    assert len(names) == len(set(names)), "so3jax.__all__ has duplicates"
    expected = public_names(so3jax) | {"scenes"}
    missing, extra = expected - set(names), set(names) - expected
    assert not missing, f"add to so3jax.__all__ (so3jax/__init__.py): {sorted(missing)}"
    assert not extra, f"so3jax.__all__ names what so3jax does not export: {sorted(extra)}"


def test_api_reference_covers_so3jax():
    want = {f"so3jax.{n}" for n in public_names(so3jax) | (set(so3jax.__all__) - {"scenes"})}
    missing = sorted(want - documented())
    assert not missing, (
        "public names without an entry in the API reference; add a ':::' line for each "
        f"to a page in docs/api/: {missing}"
    )


def test_api_reference_covers_scenes():
    want = {f"so3jax.scenes.{n}" for n in public_names(so3jax.scenes)}
    missing = sorted(want - documented())
    assert not missing, (
        "public names of so3jax.scenes without an entry in the API reference; add a "
        f"':::' line for each to docs/api/scenes.md: {missing}"
    )


def test_api_reference_names_exist():
    # A stale entry would fail the docs build; say which one here, faster.
    for path in sorted(documented()):
        obj = so3jax
        assert path.split(".")[0] == "so3jax", f"{path}: the API pages document so3jax only"
        for part in path.split(".")[1:]:
            assert hasattr(obj, part), f"docs/api names {path}, which does not exist"
            obj = getattr(obj, part)


def test_every_notebook_is_in_the_site_nav():
    config = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    for nb in sorted((ROOT / "notebooks").glob("*.ipynb")):
        assert f"notebooks/{nb.name}" in config, (
            f"add notebooks/{nb.name} to the Notebooks section of the nav in mkdocs.yml"
        )


def test_every_page_is_in_the_site_nav():
    config = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    for page in sorted((ROOT / "docs").rglob("*.md")):
        rel = page.relative_to(ROOT / "docs").as_posix()
        assert rel in config, f"docs/{rel} is not in the nav of mkdocs.yml"


def test_getting_started_has_the_readme_commands():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    block = re.search(r"```bash\n(.*?)```", readme, re.DOTALL)
    assert block, "README.md has no bash block"
    page = (ROOT / "docs" / "getting-started.md").read_text(encoding="utf-8")
    assert block.group(1) in page, (
        "docs/getting-started.md must show the README's first commands exactly; copy them"
    )
