"""Polygonal aspect hashing (PAH): model-based acquisition of the target pose (seed 000 section 3.1).

Offline (:meth:`PAHDatabase.build`, section 3.1.1): a sparse, evenly spread set ``S`` of model
surface points (farthest-point subsampling of dense area-uniform samples) and every segment
``L(s_i, s_j)`` between them, stored in two tables:

- a *length table*: the undirected segments sorted by length, indexed by quantised length
  (``length_bin_m`` bins, CSR offsets), for the direct lookup of the first polygon edge;
- a *connectivity table*: the (M, M) lengths of all segments by end point, so that "the points
  at distance ``d_0k +- tol`` from the matched ``s_0`` and ``d_1k +- tol`` from ``s_1``..." is an
  AND of banded rows.

Runtime (:meth:`PAHDatabase.localize`, section 3.1.2): an N-point polygon (4-6 points) of large
area is picked from the scan by greedy farthest-point selection from a random seed point, among
the points that have scan neighbours (an isolated stray return would otherwise be picked first).
All model polygons whose pairwise distances match the scan polygon's within the tolerance are
enumerated by a partial tree traversal (first edge from the length table, each further vertex
from the connectivity rows of the vertices matched so far: vertex 0's distance band is a run of
its row sorted by length, the other vertices' rows test only that run), vectorised over the
partial matches.
Each match gives a pose ``p = R s + T`` (eq. 1) by a batched SVD; matches that are mirror images,
that show back faces to the sensor or (constrained search) that fall outside the approach corridor
are dropped before any fit check. The survivors are scored by a surface-fit precheck on a
decimated scan (an occupancy grid of the voxels near the model surface, O(1) per point), the best
few by the full O(n) check against the dense model's KD-tree, and the distinct best ones are
polished by a short ICP (one start per basin: a start near one already polished slides to the same
pose) and verified on the whole scan.

Verification (Figure 2's fit check, plus free space): besides the surface fit, every scan ray is
cast against the model under the hypothesis (one Embree call for all hypotheses); a point measured
behind the model surface along its ray (and along the rim of its beam footprint, which can
straddle an edge) is impossible under that pose. This is what tells a long
body such as CYGNSS from its half-turn flip, which fits the visible points as well. The leading
hypothesis is always verified against its near-symmetric alternatives (the turns that map the
model nearly onto itself, found once per target), so the flip competes even when no polygon
produced it (each alternative judged with the symmetry tolerance before its short ICP); a leader
whose short ICP had not settled is polished by a full ICP before more polygons are paid for.
More polygons are tried until a verified leader fits ``accept_fitness`` of the scan
with (almost) no free-space violation, or the polygon or time budget runs out (default budgets
:data:`DEFAULT_TIME_BUDGET_S` and :data:`DEFAULT_CONSTRAINED_TIME_BUDGET_S`; running out before a
hypothesis explained the scan gives ``converged=False`` and says so). The leader and runners-up in
other basins are refined by a full ICP along the measured rays (each point matched to the face its
ray crosses) and the best verified one is returned.

Several scans (:meth:`PAHDatabase.localize_scans`, section 3.1.2's "newly acquired point clouds
over time"): successive scans of one static relative pose are pooled and localized as one cloud
(in a corridor, the fit check of the matches and the short screening ICPs run on one scan's worth
of the pooled points; the verification of every hypothesis and the final ICP always on all of
them).
On sparse scans (100-300 points on a 1 m target, or on CYGNSS at tens of metres) one scan leaves
the final ICP noise-limited (Cramer-Rao bound up to 1-2 deg per axis), and leaves the small features that tell the
cubesat's bus from its quarter and half turns unsampled; two or three scans fix both.

Constrained search (section 5.3, the docking case): a :class:`PoseConstraint` bounds the attitude
about a nominal one and the position to a cone about the boresight and a range interval. The tree
is pruned as early as possible: every polygon edge must point, once rotated by the nominal
attitude, within the attitude tolerance of the scan edge (from the first edge on); from the first
triangle on, its pose must be admitted (attitude, and the implied target origin in the cone and
range) and the matched model normals must face the sensor; matches that differ only by
neighbouring model points are merged at the triangle; and each further vertex is the model point
nearest to where the triangle's pose puts it. The alternatives of a leader that the corridor
excludes are never tried. Constrained acquisition costs a small fraction of the unconstrained one.

The package, in the order data flows through it:

- :mod:`.constraint`: :class:`PoseConstraint`, the approach corridor;
- :mod:`.build`: the offline tables; :mod:`.fileio`: their ``.npz`` files, read with suspicion;
- :mod:`.model`: the dense model and its fit grid; :mod:`.poses`: rigid-fit helpers;
- :mod:`.polygons`: polygon selection and the banded table traversal;
- :mod:`.hypotheses`: the scan bundle and the pose hypotheses; :mod:`.verify`: surface fit,
  free space, and the screening, polishing and final ICPs; :mod:`.symmetry`: near-symmetries
  and the alternatives they give;
- :mod:`.search`: ``localize``'s loop; :mod:`.multiscan`: pooling several scans;
- :mod:`.database`: :class:`PAHDatabase`, the facade over all of them.
"""

from __future__ import annotations


from .constraint import PoseConstraint
from .database import PAHDatabase
from .fileio import PAH_FORMAT_VERSION, PAHFileError
from .search import DEFAULT_CONSTRAINED_TIME_BUDGET_S, DEFAULT_TIME_BUDGET_S

__all__ = [
    "DEFAULT_CONSTRAINED_TIME_BUDGET_S",
    "DEFAULT_TIME_BUDGET_S",
    "PAH_FORMAT_VERSION",
    "PAHDatabase",
    "PAHFileError",
    "PoseConstraint",
]
