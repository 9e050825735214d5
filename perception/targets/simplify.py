"""Dense meshes: a simplified model-side copy (quadric decimation when fast-simplification is
installed, otherwise vertex clustering) and its measured deviation from the full surface."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from perception.targets.symmetry import _area_samples


def _has_quadric_decimation() -> bool:
    try:
        import fast_simplification  # noqa: F401
    except ImportError:
        return False
    return True


def _cluster_vertices(mesh: trimesh.Trimesh, cell_m: float) -> trimesh.Trimesh:
    """Vertex clustering on a voxel grid of ``cell_m`` [m], one vertex per occupied voxel;
    collapsed and duplicate faces dropped.

    Each voxel's vertex minimises the summed squared distances to the planes of the faces around
    it (Lindstrom's out-of-core simplification): corners and edges stay sharp where the voxel's
    mean would round them off by up to a cell. Directions the planes leave free (along an edge,
    across a flat patch) keep the mean; a solution farther than a cell from it falls back to the
    mean.
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    idx = np.floor((v - v.min(axis=0)) / cell_m).astype(np.int64)
    dims = idx.max(axis=0) + 1
    lin = np.ravel_multi_index(idx.T, tuple(int(d) for d in dims))
    _, inv = np.unique(lin, return_inverse=True)
    inv = inv.reshape(-1)
    n_c = int(inv.max()) + 1
    count = np.bincount(inv, minlength=n_c).astype(np.float64)
    mean = np.column_stack([np.bincount(inv, weights=v[:, k], minlength=n_c) for k in range(3)])
    mean /= count[:, None]
    # Area-weighted plane quadrics of the faces, summed into the voxel of each of their corners.
    nrm = np.asarray(mesh.face_normals, dtype=np.float64)
    w = np.asarray(mesh.area_faces, dtype=np.float64)
    off = np.einsum("ij,ij->i", nrm, v[faces[:, 0]])
    corner = inv[faces].ravel()
    A = np.empty((n_c, 3, 3))
    b = np.empty((n_c, 3))
    for i in range(3):
        b[:, i] = np.bincount(corner, weights=np.repeat(w * nrm[:, i] * off, 3), minlength=n_c)
        for j in range(i, 3):
            A[:, i, j] = A[:, j, i] = np.bincount(
                corner, weights=np.repeat(w * nrm[:, i] * nrm[:, j], 3), minlength=n_c
            )
    lam, U = np.linalg.eigh(A)
    keep = lam > 1e-3 * np.maximum(lam[:, -1:], 1e-300)
    r = b - np.einsum("cij,cj->ci", A, mean)
    coef = np.where(keep, np.einsum("cji,cj->ci", U, r) / np.where(keep, lam, 1.0), 0.0)
    step = np.einsum("cij,cj->ci", U, coef)
    far = np.linalg.norm(step, axis=1) > cell_m
    verts = mean + np.where(far[:, None], 0.0, step)
    f = inv[faces]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    return trimesh.Trimesh(vertices=verts, faces=f[np.sort(first)], process=True)


def _decimate(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """At most ``max_faces`` faces: quadric decimation when fast-simplification is installed,
    otherwise vertex clustering with the cell grown until the count fits."""
    if _has_quadric_decimation():
        return mesh.simplify_quadric_decimation(face_count=max_faces)
    # About three faces per cell-sized patch of surface on a fine mesh.
    cell = math.sqrt(3.0 * float(mesh.area) / max_faces)
    for _ in range(8):
        out = _cluster_vertices(mesh, cell)
        if len(out.faces) <= max_faces:
            return out
        cell *= 1.05 * math.sqrt(len(out.faces) / max_faces)
    return out


def _surface_deviation(
    original: trimesh.Trimesh, simplified: trimesh.Trimesh, n: int = 4_000, k: int = 16
) -> float:
    """Largest distance [m] from samples of ``simplified`` (vertices and area samples) to the
    ``original`` surface.

    Each sample is projected onto the ``k`` original faces with the nearest centroids: an upper
    bound on its distance to the surface (exact on meshes finer than the sample spacing).
    """
    rng = np.random.default_rng(0)
    sv = np.asarray(simplified.vertices)
    pick = rng.choice(len(sv), size=min(n, len(sv)), replace=False)
    pts = np.vstack([sv[np.sort(pick)], _area_samples(simplified, n, rng)])
    tri = np.asarray(original.triangles, dtype=np.float64)
    kk = min(k, len(tri))
    _, near = cKDTree(tri.mean(axis=1)).query(pts, k=kk)
    near = np.asarray(near).reshape(len(pts), kk)
    q = trimesh.triangles.closest_point(tri[near.ravel()], np.repeat(pts, kk, axis=0))
    d = np.linalg.norm(q - np.repeat(pts, kk, axis=0), axis=1).reshape(len(pts), kk)
    return float(d.min(axis=1).max())


def _simplify(path: Path, mesh: trimesh.Trimesh, max_faces: int) -> tuple[trimesh.Trimesh, float]:
    """A simplified copy of a dense mesh and its deviation [m]; warns with both."""
    simplified = _decimate(mesh, max_faces)
    if len(simplified.faces) == 0 or not float(simplified.area) > 0:
        raise ValueError(
            f"target mesh file {path}: simplifying {len(mesh.faces)} faces to {max_faces} left no"
            " surface; raise max_model_faces"
        )
    deviation = _surface_deviation(mesh, simplified)
    method = "quadric decimation" if _has_quadric_decimation() else "vertex clustering"
    warnings.warn(
        f"target mesh file {path}: {len(mesh.faces)} faces > max_model_faces={max_faces}; ICP and"
        f" PAH use a {len(simplified.faces)}-face {method} copy (deviation up to"
        f" {deviation * 1e3:.1f} mm from the surface), the sensor the full mesh",
        UserWarning,
        stacklevel=3,
    )
    return simplified, deviation
