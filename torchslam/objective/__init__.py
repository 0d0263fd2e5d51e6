"""The objective: a sum of terms over poses and points.

- :mod:`.data`: the ICP-SLAM point observations (:class:`PointMapData`: observations,
  weights or information, robust kernel, fixed variables, the terms), their whitening, their
  checks, and the functional residuals and cost the solver evaluates;
- :mod:`.terms`: the terms (point observations, relative poses, priors, user terms over
  poses and points) and the one place that differentiates a residual (``jacrev`` at zero);
- :mod:`.gauge`: what the observations and terms determine (ill-posed variables held fixed).

:class:`torchslam.PointMapProblem` (:mod:`torchslam.problem`) holds an objective's data and
its variables as an ``nn.Module``.
"""

from __future__ import annotations

from torchslam.objective import data, gauge, terms
from torchslam.objective.data import PointMapData
from torchslam.objective.terms import PointObservationTerm, PosePriorTerm, RelativePoseTerm, Term

__all__ = [
    "PointMapData",
    "PointObservationTerm",
    "PosePriorTerm",
    "RelativePoseTerm",
    "Term",
    "data",
    "gauge",
    "terms",
]
