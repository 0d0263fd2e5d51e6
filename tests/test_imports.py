"""``import torchslam`` stays cheap: the heavy modules load on first use (issue 16).

Checked by what a fresh interpreter has imported, not by timing (timings depend on the machine).
"""

import subprocess
import sys

HEAVY = ("pytorch_kinematics", "scipy", "matplotlib", "lxml", "absl", "pykdtree", "threadpoolctl")


def _modules_after(code: str) -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", f"{code}\nimport sys\nprint(' '.join(sys.modules))"],
        capture_output=True,
        text=True,
        check=True,
    )
    return set(out.stdout.split())


def test_import_torchslam_does_not_import_heavy_modules():
    loaded = _modules_after("import torchslam")
    assert not {m for m in loaded if m.split(".")[0] in HEAVY}


def test_subpackages_load_on_first_attribute_access():
    loaded = _modules_after("import torchslam\ntorchslam.posegraph\ntorchslam.registration")
    assert "torchslam.posegraph" in loaded and "torchslam.registration" in loaded
    import torchslam

    assert {"posegraph", "registration", "io", "data"} <= set(dir(torchslam))


def test_conversions_do_not_import_the_pytorch_kinematics_package():
    # The rotation conversions come from pytorch-kinematics' file, without its __init__.
    loaded = _modules_after(
        "import torch, torchslam\n"
        "torchslam.convert.quaternion_to_matrix(torch.tensor([1.0, 0.0, 0.0, 0.0]))"
    )
    assert "pytorch_kinematics" not in loaded and "matplotlib" not in loaded


def test_command_line_parser_does_not_import_registration_or_matplotlib():
    # `torchslam posegraph …` and `torchslam --help` need neither the registration stack
    # (SciPy's KD-tree) nor matplotlib.
    loaded = _modules_after("import torchslam.cli\ntorchslam.cli._parser()")
    assert "torchslam.registration" not in loaded
    assert not {m for m in loaded if m.split(".")[0] == "matplotlib"}
