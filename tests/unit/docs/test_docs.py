"""The documentation stays usable: every relative link resolves, the settings page is current,
the README stays a front page."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
PAGES = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").rglob("*.md")),
         *sorted((ROOT / "service").rglob("README.md")), ROOT / "docker" / "README.md"]
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)|!\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces → hyphens."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text(encoding="utf-8"))
    return {_slug(m.group(1)) for m in re.finditer(r"^#+\s+(.*)$", text, re.M)}


def _links(page: Path) -> list[str]:
    text = FENCE.sub("", page.read_text(encoding="utf-8"))
    text = re.sub(r"`[^`\n]*`", "", text)
    return [m.group(1) or m.group(2) for m in LINK.finditer(text)]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page):
    broken = []
    for url in _links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", url):
            continue  # http(s), mailto: not checked offline
        path, _, fragment = url.partition("#")
        target = (page.parent / path).resolve() if path else page
        if not target.exists():
            broken.append(url)
        elif fragment and target.suffix == ".md" and fragment not in _anchors(target):
            broken.append(url)
    assert not broken, f"{page.relative_to(ROOT)}: links that do not resolve: {broken}"


def test_settings_reference_is_current():
    from service.cli.settings_reference import render

    committed = (ROOT / "docs" / "settings.md").read_text(encoding="utf-8")
    assert committed == render(), (
        "docs/settings.md is stale: run `python -m service.cli.settings_reference > docs/settings.md`")


def test_every_setting_is_described():
    from service.settings import GROUPS

    missing = [name for model in GROUPS.values() for name, field in model.model_fields.items()
               if not (field.description or "").strip()]
    missing += [group for group, model in GROUPS.items() if not (model.__doc__ or "").strip()]
    assert not missing, f"settings without a description (the reference is generated from them): {missing}"


def test_readme_is_a_front_page():
    size = len((ROOT / "README.md").read_bytes())
    assert size <= 12_000, f"README.md is {size} bytes; the front page stays ≤ 12 kB, the rest lives in docs/"


def test_the_service_map_names_every_folder_and_module():
    """service/README.md's architecture block is a map of the tree: every package and module of service/ is on it."""
    readme = (ROOT / "service" / "README.md").read_text(encoding="utf-8")
    section = readme[readme.index("## Architecture"):]
    block = section[section.index("```\nservice/"):]
    block = block[:block.index("\n```", 4)]
    words = set(re.findall(r"[A-Za-z_]+(?:\.py)?/?", block))
    missing = []
    for path in sorted((ROOT / "service").rglob("*")):
        if "__pycache__" in path.parts or "static" in path.parts or path.name == "__init__.py":
            continue
        if path.is_dir() and (path / "__init__.py").is_file():
            wanted = {f"{path.name}/"}
        elif path.suffix == ".py":
            wanted = {path.name, path.stem}  # a module by file name, or by stem in its folder's list
        else:
            continue
        if not wanted & words:
            missing.append(str(path.relative_to(ROOT)))
    assert not missing, f"service/README.md's architecture map lacks: {missing}"
