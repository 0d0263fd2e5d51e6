"""Lie groups SO(3) and SE(3) (``so3``, ``se3``) and conversions (``convert``).

Tangent ordering ξ = (ω, v), rotation first, as in the seed; right perturbation T·Exp(δ).
"""

from torchslam.lie import convert, se3, so3

__all__ = ["convert", "se3", "so3"]
