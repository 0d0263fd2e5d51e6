"""torchslam: ICP-SLAM as batched, differentiable nonlinear least squares on SE(3)."""

from torchslam._checks import validation
from torchslam.lie import se3, so3

__version__ = "0.1.0"

__all__ = ["__version__", "se3", "so3", "validation"]
