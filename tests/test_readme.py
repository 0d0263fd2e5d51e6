"""README examples are executed, so they cannot rot (issue 8)."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parent.parent / "README.md"
# A block preceded by the line "<!-- readme-test: slow -->" runs only with TORCHSLAM_README_SLOW=1.
FOUND = re.findall(
    r"(<!-- readme-test: slow -->\n)?```python\n(.*?)```",
    README.read_text(encoding="utf-8"),
    re.DOTALL,
)
BLOCKS = [block for _, block in FOUND]
SLOW = [bool(marker) for marker, _ in FOUND]


def test_readme_has_python_examples():
    assert len(BLOCKS) >= 2


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_example_runs(index, capsys):
    if SLOW[index] and os.environ.get("TORCHSLAM_README_SLOW") != "1":
        pytest.skip("slow README example: set TORCHSLAM_README_SLOW=1 to run it")
    namespace: dict = {"__name__": f"readme_example_{index}"}
    exec(compile(BLOCKS[index], f"README.md[python block {index}]", "exec"), namespace)


def test_readme_setup_has_exactly_two_commands():
    section = README.read_text(encoding="utf-8").split("<!-- setup:begin -->")[1]
    section = section.split("<!-- setup:end -->")[0]
    lines = [ln for ln in section.splitlines() if ln and not ln.startswith("```")]
    assert len(lines) == 2
    assert '"torch==2.13.0"' in lines[0] and "-e" in lines[0]
    assert "pytest" in lines[1]
