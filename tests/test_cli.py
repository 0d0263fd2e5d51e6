"""The ``torchslam`` command: the demo works, and bad input never gives a traceback (issue 8)."""

from __future__ import annotations

import subprocess
import sys

import pytest


def run_cli(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "torchslam", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=300,
    )


def test_demo_small_writes_figure_and_summary(tmp_path):
    out = tmp_path / "figures"
    proc = run_cli("demo", "--poses", "12", "--points", "300", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    assert (out / "demo.png").stat().st_size > 10_000
    lines = proc.stdout.splitlines()
    assert any(line.strip().startswith("1 ") for line in lines)  # a progress line per iteration
    summary = next(line for line in lines if line.startswith("rotation error"))
    initial, optimized = (float(part.split("/")[0]) for part in summary.split()[-6::3][:2])
    assert optimized < 0.1 * initial
    assert "CONVERGED" in proc.stdout


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (("demo", "--poses", "-3"), "positive integer"),
        (("demo", "--points", "abc"), "positive integer"),
        (("demo", "--noise", "-0.1"), "≥ 0"),
        (("demo", "--visible-fraction", "1.5"), "fraction"),
        (("demo", "--jacobian", "numeric"), "invalid choice"),
        (("demo", "--poses", "2"), "--poses must be ≥ 3"),
        (("bench", "--cases", "XL"), "invalid choice"),
        (("bench", "--repeats", "0"), "--repeats must be ≥ 1"),
        (("frobnicate",), "invalid choice"),
    ],
)
def test_bad_input_is_one_line_error_without_traceback(args, fragment, tmp_path):
    proc = (
        run_cli(*args, "--out", str(tmp_path)) if args[0] in ("demo", "bench") else run_cli(*args)
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert fragment in proc.stderr
    error_lines = [line for line in proc.stderr.splitlines() if "error" in line]
    assert len(error_lines) == 1


@pytest.mark.parametrize("command", ["demo", "bench"])
def test_help(command):
    proc = run_cli(command, "--help")
    assert proc.returncode == 0
    assert "usage: torchslam" in proc.stdout
