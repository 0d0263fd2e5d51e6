"""What the command line says when input is bad: no library function names, no Python
syntax, and a warning for quaternions that are not unit (issue 28 §6)."""

from __future__ import annotations

import warnings

import pytest

from torchslam import cli
from torchslam.io import g2o


def test_missing_file_says_what_not_which_function(tmp_path, capsys):
    for command, name in (("ba", "x.txt"), ("posegraph", "x.g2o")):
        assert cli.main([command, str(tmp_path / name)]) == 2
        err = capsys.readouterr().err
        assert f"torchslam {command}: error: no such file" in err
        assert str(tmp_path / name) in err
        for internal in ("Errno", "read_bal", "read_g2o", "parse_g2o"):
            assert internal not in err


def test_reader_hints_are_command_line_options(tmp_path, capsys):
    path = tmp_path / "bad.g2o"
    path.write_text(
        "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
        "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 -1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1\n"
    )
    assert cli.main(["posegraph", str(path), "--information", "strict"]) == 2
    err = capsys.readouterr().err
    assert "--information strict" in err and "--information repair" in err
    assert "information='" not in err


@pytest.mark.parametrize("w", ["2", "5", "1.01"])
def test_quaternion_of_norm_not_one_warns(tmp_path, w):
    path = tmp_path / "q.g2o"
    path.write_text(f"VERTEX_SE3:QUAT 0 0 0 0 0 0 0 {w}\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n")
    with pytest.warns(
        UserWarning,
        match=r"1 of 2 vertices have a quaternion whose norm is not 1 \(the first on line 1\)",
    ):
        graph = g2o.read_g2o(path)
    assert float(graph.poses[0, 0, 0]) == 1.0  # normalized: the identity


def test_unit_quaternions_within_print_precision_are_silent(tmp_path):
    path = tmp_path / "q.g2o"
    # 6 significant digits of a unit quaternion: norm 1 within 1e-6
    path.write_text("VERTEX_SE3:QUAT 0 0 0 0 0.707107 0 0 0.707107\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        g2o.read_g2o(path)
