"""BAL files: round trip, the real Ladybug file, bad files with errors naming file and line."""

from __future__ import annotations

import bz2

import pytest
import torch

from tests.helpers import dataset_folder
from torchslam.io.bal import BALProblem, read_bal, write_bal

DATA = dataset_folder("bal-ladybug-21")

SMALL = """2 3 4
0 0 -1.5e+01 2.0
0 1 3.25 -4.5
1 1 0.5 0.25
1 2 -7 8
""" + "\n".join(
    str(v)
    for v in (
        *(0.01, -0.02, 0.03, 0.1, 0.2, -3.0, 500.0, -1e-7, 2e-13),
        *(0.0, 0.0, 0.0, -0.1, 0.0, -2.5, 480.0, 0.0, 0.0),
        *(0.1, 0.2, 1.0, -0.3, 0.4, 1.5, 0.0, -0.5, 2.0),
    )
)


def test_read_small_file_and_round_trip(tmp_path):
    path = tmp_path / "small.txt"
    path.write_text(SMALL + "\n")
    problem = read_bal(path)
    assert problem.cameras.shape == (2, 9) and problem.points.shape == (3, 3)
    assert problem.camera_index.tolist() == [0, 0, 1, 1]
    assert problem.point_index.tolist() == [0, 1, 1, 2]
    assert problem.observations[0].tolist() == [-15.0, 2.0]
    assert problem.cameras[0, 8].item() == 2e-13
    write_bal(tmp_path / "again.txt", problem)
    again = read_bal(tmp_path / "again.txt")
    for name in ("cameras", "points", "camera_index", "point_index", "observations"):
        assert torch.equal(getattr(again, name), getattr(problem, name)), name  # exact: repr
    # values spread over lines in any way, and bz2 files, read the same
    values_on_one_line = [*SMALL.split("\n")[:5], " ".join(SMALL.split("\n")[5:])]
    (tmp_path / "one.txt").write_text("\n".join(values_on_one_line))
    assert torch.equal(read_bal(tmp_path / "one.txt").cameras, problem.cameras)
    (tmp_path / "small.txt.bz2").write_bytes(bz2.compress(SMALL.encode()))
    assert torch.equal(read_bal(tmp_path / "small.txt.bz2").points, problem.points)


def test_residuals_follow_the_snavely_convention(tmp_path):
    path = tmp_path / "small.txt"
    path.write_text(SMALL)
    problem = read_bal(path)
    T = problem.poses[0]
    X = problem.points[0]
    P = T[:3, :3] @ X + T[:3, 3]
    p = -P[:2] / P[2]
    f, k1, k2 = problem.cameras[0, 6:].tolist()
    r2 = float(p.square().sum())
    predicted = f * (1 + k1 * r2 + k2 * r2 * r2) * p
    torch.testing.assert_close(problem.residuals()[0], predicted - problem.observations[0])
    assert problem.cost() == pytest.approx(0.5 * float(problem.residuals().square().sum()))


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data/bal")
def test_real_ladybug_file():
    problem = read_bal(DATA / "problem-21-11315-pre.txt")
    assert problem.cameras.shape == (21, 9) and problem.points.shape == (11315, 3)
    assert problem.observations.shape == (36455, 2)
    # Ceres' initial cost of this file (½ Σ r², every library reports the same): 4.413239e6
    assert problem.cost() == pytest.approx(4.413239e6, rel=1e-6)


@pytest.mark.parametrize(
    ("text", "fragments"),
    [
        ("", ["empty"]),
        ("2 3\n", ["line 1", "2 fields"]),
        ("2 x 4\n", ["line 1", "'x'"]),
        (SMALL.replace("0 1 3.25 -4.5", "0 1 3.25"), ["line 3", "3 fields"]),
        (SMALL.replace("0 1 3.25 -4.5", "0 1 3.25 nan"), ["line 3", "finite"]),
        (SMALL.replace("1 2 -7 8", "1 3 -7 8"), ["line 5", "point index"]),
        (SMALL.replace("1 2 -7 8", "2 2 -7 8"), ["line 5", "camera index"]),
        (SMALL.replace("500.0", "5OO"), ["line 12", "'5OO'"]),
        (SMALL.rsplit("\n", 2)[0], ["truncated", "25 of 27"]),
        (SMALL + "\n1.0", ["line 33", "beyond"]),
        ("2 3 4\n0 0 1 2\n", ["truncated", "1 of 4 observations"]),
    ],
)
def test_bad_files_name_file_and_line(text, fragments, tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(ValueError) as raised:
        read_bal(path)
    message = str(raised.value)
    assert message.startswith("read_bal: ") and "bad.txt" in message
    for fragment in fragments:
        assert fragment in message, (fragment, message)


def test_bad_arguments(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_bal(tmp_path / "missing.txt")
    with pytest.raises(TypeError, match="BALProblem"):
        write_bal(tmp_path / "x.txt", "not a problem")
    nan = BALProblem(
        torch.full((1, 9), float("nan"), dtype=torch.float64),
        torch.zeros(1, 3, dtype=torch.float64),
        torch.zeros(1, dtype=torch.int64),
        torch.zeros(1, dtype=torch.int64),
        torch.zeros(1, 2, dtype=torch.float64),
    )
    with pytest.raises(ValueError, match="finite"):
        write_bal(tmp_path / "x.txt", nan)
