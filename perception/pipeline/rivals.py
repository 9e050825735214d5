"""The rival monitor of a track: a registration the filter's gate rejected may be the right pose.

The gate rejects a sound registration when the filter and the registration disagree beyond both
covariances. One of them is wrong, and nothing yet says which: an unmodelled manoeuvre or a
registration in ICP's wrong basin, or a filter that followed a wrong basin and now rejects the
right one. A restart on several rejected registrations in a row settles it when they keep
coming; between single rejections the track used to be published as if the question were closed.

On a flat face seen close in, the registrations that pin the in-plane position are few and come
from a handful of features. PAH restarted a hubble track at 4.4 m in a false basin 10 cm off in
the face's plane, under ICP's millimetre covariance (the curvature of its basin, not the distance
to the next one). The right basin's registrations were rejected every few frames while those of
the false basin were accepted, and the filter, sure again, published six frames valid 9 cm off
under a 4.5-5.3 cm protection level (reset seed 923, ``final_approach``).

So a rejected sound registration becomes the track's **rival**: the filter's state moved onto the
registration along the directions it observes (:meth:`PoseFilter.moved_to
<perception.pipeline.filter.PoseFilter.moved_to>`; along the ones it leaves unobserved its pose is
wherever ICP left it and says nothing), carried with the track's rates. While a rival stands, the
protection level grows by the port's offset between the two, as it does for a twin the scan cannot
rule out (:mod:`~perception.pipeline.twins`). It falls once ``integrity.rival_votes`` accepted
registrations have each been beyond the gate from it (registrations that do not observe the
disputed direction cannot rule it out, and do not count); a newer rejection replaces it. A rival
that comes back before it fell needs twice the votes it needed: registrations that keep landing
in two places are two basins, not an outlier, and the accepted ones of the wrong basin vote as
readily as the right one's (on hubble one in two of the registrations that saw the disputed
direction took each basin). A restart on the rejected registrations makes the track it replaced
the rival, judged afresh.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from perception.pipeline.filter import PoseFilter
    from perception.pipeline.tridar import TriDAR

FloatArray = npt.NDArray[np.float64]

__all__ = ["MAX_RETURNS", "RivalMonitor"]

#: Returns beyond this many no longer double the votes a rival needs (2**10 times
#: ``rival_votes`` is longer than any approach's tracking).
MAX_RETURNS = 10


class RivalMonitor:
    """The rival monitor of the pipeline's track (see the module docstring).

    Attributes:
        rival: the standing rival (a :class:`~perception.pipeline.filter.PoseFilter` at the time of
            the registration it came from), or None.
        votes: accepted registrations since the rival stood that were beyond the gate from it.
        returns: rejections that replaced a standing rival since one last fell (each doubles the
            votes the rival needs).

    Args:
        tri: the pipeline (its ``pc.integrity.rival_votes``; None: the monitor is off).
    """

    def __init__(self, tri: TriDAR) -> None:
        self.tri = tri
        self.reset()

    def reset(self) -> None:
        """No rival (a new track, a lost one, a new run)."""
        self.rival: PoseFilter | None = None
        self.votes = 0
        self.returns = 0

    @property
    def enabled(self) -> bool:
        return self.tri.pc.integrity.rival_votes is not None

    def rejected(self, f: PoseFilter, T_meas: FloatArray, cov_pose: FloatArray) -> None:
        """The gate of ``f`` (predicted to the registration's time by the rejected update)
        rejected the sound registration ``T_meas`` (target origin) with covariance
        ``cov_pose``: it stands as the rival."""
        if self.enabled:
            if self.rival is not None:
                self.returns = min(self.returns + 1, MAX_RETURNS)
            self.rival = f.moved_to(T_meas, cov_pose)
            self.votes = 0

    def replaced(self, old: PoseFilter) -> None:
        """The track was restarted on its rejected registrations: the track it replaced (``old``)
        stands as the rival."""
        if self.enabled:
            self.rival = old.copy()
            self.votes = 0
            self.returns = 0

    def accepted(self, t: float, T_meas: FloatArray, cov_pose: FloatArray) -> None:
        """The filter accepted the registration ``T_meas`` taken at ``t`` [s] (covariance
        ``cov_pose``): a vote against the rival when it is beyond the gate from it too."""
        rival = self.rival
        if rival is None:
            return
        if rival.mahalanobis2(max(float(t), rival.t), T_meas, cov_pose) > rival.gate:
            self.votes += 1
        if self.votes >= self.needed:
            self.reset()

    @property
    def needed(self) -> int:
        """Votes the standing rival needs to fall: ``rival_votes``, doubled for each return."""
        votes = self.tri.pc.integrity.rival_votes
        return 0 if votes is None else int(votes) << self.returns

    def offset_m(self, f: PoseFilter) -> float:
        """The port's offset [m] between the track ``f`` and the rival at ``f``'s time (0 with no
        rival)."""
        rival = self.rival
        if rival is None or not f.initialized:
            return 0.0
        t = max(f.t, rival.t)
        a, b = f.pose_at(t), rival.pose_at(t)
        r = f.r
        return float(np.linalg.norm(a[:3, :3] @ r + a[:3, 3] - b[:3, :3] @ r - b[:3, 3]))
