"""What a PAH search carries: the scan bundle (:class:`_Scan`), the pose hypotheses
(:class:`_Hypothesis`) and how they are ranked and accepted (:func:`_best`, score, free-space
allowance)."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from .constraint import PoseConstraint
from .poses import FloatArray, IntArray

# Free-space test: a point further than 3 sigma + this [m] behind the model surface along its
# ray is a violation (the margin absorbs mixed returns of the beam footprint at silhouettes).
_FREE_SPACE_MARGIN_M = 0.02
# A hypothesis with more violations than this fraction of the scan is not accepted outright.
_FREE_SPACE_ACCEPT = 0.02
_FREE_SPACE_ACCEPT_POINTS = 3.5
# Score price of an outlier or a free-space violation, in units of one point's likelihood (<= 1):
# a missing or see-through point is evidence against the pose, not just a poorer fit.
_UNEXPLAINED_PENALTY = 2.0


@dataclass(eq=False)
class _Scan:
    """The finite scan points of one :meth:`PAHDatabase.localize` call and what verification needs.

    Attributes:
        P: (n, 3) points [m], sensor frame.
        sigma: (n,) range noise [m].
        ranges: (n,) ``|P|`` [m].
        rays: (n, 3) unit ray directions.
        gate: (n,) inlier distance to the model surface [m] (noise plus model sampling).
        margin: (n,) depth behind the model surface beyond which a point violates free space [m].
    """

    P: FloatArray
    sigma: FloatArray
    ranges: FloatArray
    rays: FloatArray
    gate: FloatArray
    margin: FloatArray

    @classmethod
    def build(cls, P: FloatArray, sigma: FloatArray, rays: FloatArray | None, spacing: float,
              ranges: FloatArray | None = None) -> _Scan:
        """The scan of points ``P`` with range noise ``sigma``: gate ``3 sigma + spacing`` (the
        model's sample spacing), free-space margin ``3 sigma + _FREE_SPACE_MARGIN_M``; rays are
        the lines of sight when None."""
        r = np.linalg.norm(P, axis=1) if ranges is None else ranges
        d = P / r[:, None] if rays is None else rays
        return cls(P, sigma, r, d, 3.0 * sigma + spacing, 3.0 * sigma + _FREE_SPACE_MARGIN_M)

    def subset(self, idx: IntArray) -> _Scan:
        """The points ``idx`` of this scan, with their gates and margins."""
        return _Scan(*(getattr(self, f.name)[idx] for f in fields(self)))


@dataclass
class _Hypothesis:
    """A candidate pose after a short ICP, verified on the whole scan (:func:`.verify._verify`).

    Attributes:
        T: (4, 4) pose ``T_sensor_target``.
        fitness: fraction of the scan points within their noise gate of the model surface.
        likelihood: mean Gaussian likelihood of the point-to-plane residuals (0 for outliers).
        free_space: fraction of the scan points measured behind the model surface along their
            ray (the ray would have been stopped by the model first): impossible under this pose.
        expanded: its near-symmetric alternatives have been verified too.
        settled: its short ICP converged (an unsettled pose, still sliding along a weakly
            observed direction, scores below what it would reach).
        polished: refined by a full ICP on every point (:func:`.verify._polish`).
        free_space_beam: violation fraction judged over the beam footprint, once computed (it
            can only be lower than ``free_space``).
    """

    T: FloatArray
    fitness: float
    likelihood: float
    free_space: float
    expanded: bool = False
    settled: bool = True
    polished: bool = False
    free_space_beam: float | None = None

    @property
    def score(self) -> float:
        """Ranking score: likelihood, less a heavy price per unexplained or see-through point."""
        return self.likelihood - _UNEXPLAINED_PENALTY * ((1.0 - self.fitness) + self.free_space)

    def clean(self, accept_fitness: float, n_points: int) -> bool:
        """Explains the scan: ``accept_fitness`` of it fits and (almost) nothing sees through it.

        A few violations are tolerated (mixed returns at silhouettes): up to
        ``_FREE_SPACE_ACCEPT`` of the scan, and at least ``_FREE_SPACE_ACCEPT_POINTS`` points.
        """
        fs = self.free_space if self.free_space_beam is None else self.free_space_beam
        return self.fitness >= accept_fitness and fs <= _free_space_allowed(n_points)


def _free_space_allowed(n_points: int) -> float:
    """Violation fraction a pose that explains a scan of ``n_points`` may show (silhouettes)."""
    return max(_FREE_SPACE_ACCEPT, _FREE_SPACE_ACCEPT_POINTS / max(n_points, 1))


def _best(hyps: list[_Hypothesis], constraint: PoseConstraint | None) -> _Hypothesis | None:
    """Highest-scoring hypothesis (inside the corridor, if any); the first one on ties."""
    best = None
    for h in hyps:
        if constraint is not None and not constraint.admits(h.T):
            continue
        if best is None or h.score > best.score:
            best = h
    return best
