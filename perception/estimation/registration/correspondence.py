"""Correspondences of ICP: which model face each scan point lies on, and when that is ambiguous.

:func:`correspond` pairs points (target frame) with the model within a gate: with a
:class:`FaceGrid`, the closest exact face (or the face its measured ray crosses) and, past the
grid's band, the nearest surface sample; without one, the nearest sample or the best tangent plane
among the few nearest. :func:`edge_ambiguous` flags the grazing matches another face of the model
explains as well (edge mixing), which inform no direction of the pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from perception.estimation.registration.model import ModelCloud

FloatArray = npt.NDArray[np.float64]


def _best_plane_match(
    mc: ModelCloud, q: FloatArray, gate: float, k: int
) -> tuple[FloatArray, npt.NDArray[np.intp]]:
    """Among the ``k`` nearest samples, the one whose tangent plane passes closest to the point.

    Near an edge the nearest sample often lies on the neighbouring face; its plane is wrong for the
    point and biases the pose by a fraction of the model spacing. Returns the Euclidean distance to
    the chosen sample (inf where none is within ``gate``) and its index. Used for models without a
    :class:`FaceGrid`.
    """
    dist, idx = mc.kdtree.query(q, k=k, distance_upper_bound=gate, workers=1)
    ok = np.isfinite(dist)
    safe = np.where(ok, idx, 0)
    r = np.abs(np.einsum("ijk,ijk->ij", mc.normals[safe], q[:, None, :] - mc.points[safe]))
    r = np.where(ok, r, np.inf)
    best = np.argmin(r, axis=1)
    rows = np.arange(q.shape[0])
    return dist[rows, best], idx[rows, best]


@dataclass
class Matches:
    """Correspondences of the scan points ``sel`` (target frame): distance to the model [m],
    unit normal, matched surface point and signed point-to-plane residual ``n . (q - foot)`` [m]."""

    sel: npt.NDArray[np.intp]
    dist: FloatArray
    normal: FloatArray
    foot: FloatArray
    r: FloatArray

    def keep(self, m: npt.NDArray[np.bool_]) -> Matches:
        return Matches(self.sel[m], self.dist[m], self.normal[m], self.foot[m], self.r[m])


def _samples_match(mc: ModelCloud, q: FloatArray, rows: npt.NDArray[np.intp], gate: float,
                   k: int) -> Matches:
    """Nearest-sample matches of the points ``rows`` (best tangent plane of ``k`` when ``k`` > 1)."""
    if k > 1:
        dist, idx = _best_plane_match(mc, q[rows], gate, k)
    else:
        dist, idx = mc.kdtree.query(q[rows], k=1, distance_upper_bound=gate, workers=1)
    ok = np.isfinite(dist)
    j = idx[ok]
    sel = rows[ok]
    nrm = mc.normals[j]
    foot = mc.points[j]
    r = np.einsum("ij,ij->i", nrm, q[sel] - foot)
    return Matches(sel, dist[ok], nrm, foot, r)


def correspond(
    mc: ModelCloud,
    q: FloatArray,
    gate: float,
    k: int,
    rays: FloatArray,
    back_cos: float,
    samples: bool = False,
    along_rays: bool = False,
    max_cross: FloatArray | None = None,
) -> Matches:
    """Matches of the points ``q`` (N, 3, target frame) within ``gate`` [m] of the model.

    With a :class:`FaceGrid`: the closest face (exact plane; the matched point is the closest
    point of the facet), and for points beyond the grid's band (only when ``gate`` reaches past
    it) the nearest sample, whose plane is its face's. Without one, or with ``samples`` (the
    point-to-point baseline pairs points with samples): the nearest sample, or the best tangent
    plane among the ``k`` nearest.
    """
    g = mc.grid
    if g is None or samples:
        return _samples_match(mc, q, np.arange(q.shape[0]), gate, k)
    found, dist, face, v = g.nearest(q, rays, back_cos, along_rays, max_cross)
    ok = dist <= gate
    sel = found[ok]
    pl = g.planes[face[ok]]
    v = v[ok]
    nrm = pl[:, 0, :3]
    r = v[:, 0]
    # Onto the plane, then back over the facet edges the point lies beyond.
    beyond = np.maximum(v[:, 1:], 0.0)
    foot = q[sel] - r[:, None] * nrm - np.einsum("ki,kij->kj", beyond, pl[:, 1:, :3])
    m = Matches(sel, dist[ok], nrm, foot, r)
    if gate > g.band and found.size < q.shape[0]:
        missed = np.ones(q.shape[0], dtype=bool)
        missed[found] = False
        far = _samples_match(mc, q, np.flatnonzero(missed), gate, 1)
        if far.sel.size:
            m = Matches(*(np.concatenate([a, b]) for a, b in zip(
                (m.sel, m.dist, m.normal, m.foot, m.r), (far.sel, far.dist, far.normal, far.foot, far.r))))
    return m


#: A grazing match (``|n . d|`` below this) is checked for edge ambiguity before it counts.
_GRAZING_COS = 0.25
#: Model normals this far apart (cosine below) are different faces for the ambiguity test.
_OTHER_FACE_COS = 0.7
#: Points along the noise band of a grazing match at which the closest face is checked.
_AMBIGUITY_STEPS = 5


def edge_ambiguous(mc: ModelCloud, foot: FloatArray, normal: FloatArray, sig: FloatArray,
                   cos_ray: FloatArray, n_sigmas: float, rays: FloatArray | None = None) -> npt.NDArray[np.bool_]:
    """Grazing matches that another face of the model explains as well: edge mixing.

    A point whose ray meets its face at a grazing angle carries a large weight in the
    information (its range noise barely moves it off that face), but near an edge the same point
    lies within the noise of the neighbouring face too: a face-on point whose noise put it a few
    centimetres below a box's front face is "on" the side face. Which face it came from is not
    known, so it pins nothing: a wrong pose of a flat face held by a strip of such points would
    otherwise look confident. A grazing match is ambiguous when, along its ray within
    ``n_sigmas`` range sigmas of its foot, the model's closest face turns to one whose normal
    differs by more than ~45 deg (exact faces of the model's :class:`FaceGrid`; without one, a
    surface sample within that distance plus the sample spacing).

    Args:
        mc: the model.
        foot: (K, 3) matched surface points, target frame.
        normal: (K, 3) their unit normals, target frame.
        sig: (K,) range sigma of the points [m].
        cos_ray: (K,) ``normal . ray direction``.
        n_sigmas: the noise band [sigmas].
        rays: (K, 3) unit rays, target frame (needed for the face test).
    """
    out = np.zeros(foot.shape[0], dtype=bool)
    g = np.flatnonzero(np.abs(cos_ray) < _GRAZING_COS)
    if g.size == 0:
        return out
    if mc.grid is None or rays is None:
        r = n_sigmas * sig[g] + mc.spacing
        dist, idx = mc.kdtree.query(foot[g], k=12, distance_upper_bound=float(r.max()))
        near = (idx < mc.points.shape[0]) & (dist <= r[:, None])
        nb = mc.normals[np.minimum(idx, mc.points.shape[0] - 1)]
        other = np.einsum("ikj,ij->ik", nb, normal[g]) < _OTHER_FACE_COS
        out[g] = np.any(near & other, axis=1)
        return out
    steps = np.linspace(-1.0, 1.0, _AMBIGUITY_STEPS)
    band = n_sigmas * sig[g]
    q = (foot[g][None, :, :] + (steps[:, None] * band)[:, :, None] * rays[g][None, :, :]).reshape(-1, 3)
    tol = np.tile(np.maximum(0.2 * band, 1e-3), steps.size)
    found, dist, face, _ = mc.grid.nearest(q, along_rays=False)
    n_face = mc.grid.planes[face][:, 0, :3]
    k = found % g.size
    other = (np.einsum("ij,ij->i", n_face, normal[g][k]) < _OTHER_FACE_COS) & (dist <= tol[found])
    out[g[np.unique(k[other])]] = True
    return out
