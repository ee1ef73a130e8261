"""One test command and one way to call ``dsareg`` across the README and the docs: a new user who follows the
README, then getting-started.md, then examples/README.md meets the same commands (issue 44: getting-started gave
another test command and ``--workers 2``, examples/ wrote bare ``dsareg``, the README ``.venv/bin/dsareg``).

The pages write commands for a shell with the venv active (``dsareg …``, ``python …``). The benchmark records
(docs/benchmarks/) keep the commands as they were run, and are not held to it."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), *sorted((ROOT / "examples").rglob("README.md")),
         ROOT / "service" / "README.md", ROOT / "docker" / "README.md"]
PAGES = [page for page in PAGES if "benchmarks" not in page.relative_to(ROOT).parts]


def _readme_test_command() -> str:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    block = readme[readme.index("# 2. install what the tests need"):]
    return block[block.index("\n") + 1:block.index("\n```")]


def test_every_page_calls_dsareg_one_way():
    """No page but the install's ``. .venv/bin/activate`` names a program inside the venv."""
    found = {}
    for page in PAGES:
        calls = re.findall(r"\.venv/bin/(?!activate\b)[\w.-]+", page.read_text(encoding="utf-8"))
        if calls:
            found[str(page.relative_to(ROOT))] = sorted(set(calls))
    assert not found, f"write `dsareg …` / `python …` (the venv active), not: {found}"


def test_one_test_command():
    command = _readme_test_command()
    assert "dsareg warmup" in command and "python -m pytest -n 2 --dist loadfile -m timed tests/system" in command
    assert command in (ROOT / "docs" / "getting-started.md").read_text(encoding="utf-8")
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    for step in re.findall(r"python -m pytest [^&\n]*", command):  # .ci/run runs the same pytest steps
        assert step.replace("'", '"').strip() in ci.replace("'", '"'), step
    others = {str(page.relative_to(ROOT)): line for page in PAGES for line in
              page.read_text(encoding="utf-8").splitlines()
              if re.search(r"\bpytest\s*(#|$|-n\b)", line) and line.strip() not in command}
    assert not others, f"another whole-suite test command: {others}"


def test_getting_started_serves_as_the_readme_does():
    page = (ROOT / "docs" / "getting-started.md").read_text(encoding="utf-8")
    assert "dsareg serve --data-dir ./dsareg-data " in page and "--workers" not in page
