"""The TriDAR box on top of the estimators: modes, the relative-motion filter, the state vector,
integrity (protection level) and the observability-aware scan planner, run frame by frame by
:class:`~perception.pipeline.tridar.TriDAR` (its frame loop) over the mode handlers (``bearing``,
``search``, ``tracking``), with the ambiguity monitor (``twins``) and the publisher (``publish``).

Public API (DESIGN.md): ``perception.pipeline.TriDAR(config, target).step(scene, t) -> StateVector``.
"""

from perception.pipeline.state import StateVector
from perception.pipeline.tridar import (
    PipelineStats,
    TriDAR,
    approach_pose,
    deskew,
    nominal_attitude,
)

__all__ = ["PipelineStats", "StateVector", "TriDAR", "approach_pose", "deskew", "nominal_attitude"]
