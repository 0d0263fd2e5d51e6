"""README and manual (docs/*.md) examples are executed, so they cannot rot (issues 8, 28 §8);
the README stays a short entry point whose links reach every page of the site."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
# The README and every page of the manual (docs/, the mkdocs site).
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]
# A block preceded by the line "<!-- readme-test: slow -->" runs only with TORCHSLAM_README_SLOW=1.
FOUND = [
    (page.relative_to(ROOT).as_posix(), k, marker, block)
    for page in PAGES
    for k, (marker, block) in enumerate(
        re.findall(
            r"(<!-- readme-test: slow -->\n)?```python\n(.*?)```",
            page.read_text(encoding="utf-8"),
            re.DOTALL,
        )
    )
]
BLOCKS = [block for *_, block in FOUND]
SLOW = [bool(marker) for _, _, marker, _ in FOUND]
NAMES = [f"{page}[{k}]" for page, k, _, _ in FOUND]


def test_readme_has_python_examples():
    assert len(BLOCKS) >= 2


@pytest.mark.parametrize("index", range(len(BLOCKS)), ids=NAMES)
def test_readme_example_runs(index, capsys):
    if SLOW[index] and os.environ.get("TORCHSLAM_README_SLOW") != "1":
        pytest.skip("slow README example: set TORCHSLAM_README_SLOW=1 to run it")
    namespace: dict = {"__name__": f"readme_example_{index}"}
    exec(compile(BLOCKS[index], f"{NAMES[index]} (python block)", "exec"), namespace)


def test_readme_setup_has_exactly_two_commands():
    section = README.read_text(encoding="utf-8").split("<!-- setup:begin -->")[1]
    section = section.split("<!-- setup:end -->")[0]
    lines = [ln for ln in section.splitlines() if ln and not ln.startswith("```")]
    assert len(lines) == 2
    assert '"torch==2.13.0"' in lines[0] and "-e" in lines[0]
    assert "pytest" in lines[1]


def test_readme_is_short_and_links_every_page():
    # a README users read top to bottom (what it is, install, one example, links), the rest
    # in the manual; every page is linked from it and listed in the site's navigation
    text = README.read_text(encoding="utf-8")
    assert len(text.split()) < 1200
    nav = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    for page in sorted((ROOT / "docs").glob("*.md")):
        assert f"](docs/{page.name})" in text, page.name
        assert f": {page.name}" in nav, page.name
