"""Localizing from several successive scans of one relative pose, pooled (seed 000 section 3.1.2).

The scans' points, noise and measured rays are pooled and localized as one cloud by
:meth:`PAHDatabase.localize`; in a corridor, the search's work per candidate runs on one scan's
worth of the pooled points (``search_points``), verification and the final ICP on all of them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from perception.estimation.registration import RegistrationResult
from perception.sensing.pointcloud import PointCloud

from .constraint import PoseConstraint

if TYPE_CHECKING:
    from .database import PAHDatabase


def localize_scans(
    db: PAHDatabase,
    scans: Sequence[PointCloud],
    rng: np.random.Generator,
    constraint: PoseConstraint | None = None,
    max_time_s: float | None = None,
) -> RegistrationResult:
    """The pose from pooled scans (see :meth:`PAHDatabase.localize_scans`); through
    ``db.localize``."""
    if isinstance(scans, PointCloud):
        scans = [scans]
    if not isinstance(scans, Sequence) or len(scans) == 0:
        raise ValueError(f"scans is {type(scans).__name__}; expected a non-empty sequence of "
                         "PointCloud")
    for i, c in enumerate(scans):
        if not isinstance(c, PointCloud):
            raise ValueError(f"scans[{i}] is a {type(c).__name__}; expected a PointCloud")  # noqa: TRY004
    P = np.concatenate([c.points for c in scans])
    sig = np.concatenate([np.broadcast_to(np.asarray(c.sigma, dtype=np.float64), (len(c),))
                          for c in scans])
    D = np.concatenate([c.directions for c in scans])
    # In a corridor the search works on one scan's worth of the pooled points (verification
    # and the final ICP on all of them); unconstrained it searches them all (the reasons are in
    # PAHDatabase.localize_scans).
    search = max(len(c) for c in scans) if constraint is not None else None
    res = db.localize(P, rng, constraint=constraint, sigma=sig, max_time_s=max_time_s,
                      directions=D, search_points=search)
    return res
