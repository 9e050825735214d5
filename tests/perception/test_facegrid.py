"""FaceGrid: the vectorised build indexes what the per-face reference build did.

``_reference_build`` is the per-face build FaceGrid had before it was vectorised (issue 16),
kept here only as the reference: the new build must give the same voxels, the same candidates
at the same distances in the same order, and so the same ``nearest`` answers, except where the
reference broke an exact tie by BLAS rounding (see :func:`_assert_equivalent`).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest
import trimesh

from perception.estimation.registration.facegrid import FaceGrid
from perception.shapes import SHAPE_KINDS, generate_target
from perception.targets import LIBRARY, load_target

FloatArray = npt.NDArray[np.float64]

_GRID_CELLS = 48
_GRID_BAND_CELLS = 3.0
_GRID_MAX_CELL_M = 0.15
_GRID_MAX_CELLS = 256
_FACET_ANGLE_RAD = 1e-6
_NO_EDGE = -1.0e30


def _triangle_distance(x: FloatArray, tri: FloatArray, normal: FloatArray) -> FloatArray:
    """Exact distances [m] of points ``x`` (M, 3) to one triangle ``tri`` (3, 3) of unit ``normal``."""
    a, b, c = tri
    inside = np.ones(x.shape[0], dtype=bool)
    best = np.full(x.shape[0], np.inf)
    for p, q in ((a, b), (b, c), (c, a)):
        e = q - p
        xp = x - p
        inside &= xp @ np.cross(e, normal) <= 0.0
        s = np.clip(xp @ e / max(float(e @ e), 1e-300), 0.0, 1.0)
        d = xp - s[:, None] * e
        best = np.minimum(best, np.einsum("ij,ij->i", d, d))
    return np.where(inside, np.abs((x - a) @ normal), np.sqrt(best))


def _reference_build(
    mesh: trimesh.Trimesh, cells: int | None = None, band_cells: float = _GRID_BAND_CELLS
) -> FaceGrid:
    """The per-face FaceGrid.build of commit 8e92198 (about 1.2 ms per face), verbatim."""
    tris = np.asarray(mesh.triangles, dtype=np.float64)
    n_faces = tris.shape[0]
    cr = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    area2 = np.linalg.norm(cr, axis=1)
    good = area2 > 1e-12 * max(float(area2.max(initial=0.0)), 1e-300)
    if not np.any(good):
        raise ValueError("mesh has no faces of non-zero area; ICP needs a surface")
    nrm = cr / np.where(good, area2, 1.0)[:, None]

    interior = np.zeros((n_faces, 3), dtype=bool)
    adj = np.asarray(mesh.face_adjacency, dtype=np.intp).reshape(-1, 2)
    if adj.size:
        cop = np.asarray(mesh.face_adjacency_angles) < _FACET_ANGLE_RAD
        shared = np.sort(np.asarray(mesh.face_adjacency_edges, dtype=np.intp), axis=1)
        fv = np.asarray(mesh.faces, dtype=np.intp)
        for side in (0, 1):
            f = adj[cop, side]
            sh = shared[cop]
            for e in range(3):
                ev = np.sort(np.stack([fv[f, e], fv[f, (e + 1) % 3]], axis=1), axis=1)
                hit = np.all(ev == sh, axis=1)
                interior[f[hit], e] = True
    facet = np.arange(n_faces)
    if adj.size and np.any(cop):
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        a = adj[cop]
        graph = coo_matrix((np.ones(len(a)), (a[:, 0], a[:, 1])), shape=(n_faces, n_faces))
        facet = connected_components(graph, directed=False)[1]

    planes = np.zeros((n_faces, 4, 4))
    planes[:, 0, :3] = nrm
    planes[:, 0, 3] = -np.einsum("ij,ij->i", nrm, tris[:, 0])
    for e in range(3):
        p, q = tris[:, e], tris[:, (e + 1) % 3]
        m = np.cross(q - p, nrm)
        m /= np.maximum(np.linalg.norm(m, axis=1), 1e-300)[:, None]
        off = -np.einsum("ij,ij->i", m, p)
        planes[:, e + 1, :3] = np.where(interior[:, e, None], 0.0, m)
        planes[:, e + 1, 3] = np.where(interior[:, e], _NO_EDGE, off)

    lo = tris.reshape(-1, 3).min(axis=0)
    hi = tris.reshape(-1, 3).max(axis=0)
    if cells is None:
        cells = int(np.clip(float((hi - lo).max()) / _GRID_MAX_CELL_M, _GRID_CELLS, _GRID_MAX_CELLS))
    h = max(float((hi - lo).max()) / int(cells), 1e-6)
    band = float(band_cells) * h
    half_diag = 0.5 * np.sqrt(3.0) * h
    reach = band + half_diag
    origin = lo - reach - h
    shape = tuple(int(v) for v in np.ceil((hi - lo + 2.0 * (reach + h)) / h))
    cell_l, face_l, dist_l = [], [], []
    for k in np.flatnonzero(good):
        t = tris[k]
        i0 = np.floor((t.min(axis=0) - reach - origin) / h).astype(np.intp)
        i1 = np.floor((t.max(axis=0) + reach - origin) / h).astype(np.intp)
        g = np.stack(
            np.meshgrid(*[np.arange(i0[d], i1[d] + 1) for d in range(3)], indexing="ij"), -1
        ).reshape(-1, 3)
        cen = origin + (g + 0.5) * h
        near = np.abs((cen - t[0]) @ nrm[k]) <= reach
        g, cen = g[near], cen[near]
        d = _triangle_distance(cen, t, nrm[k])
        keep = d <= reach
        cell_l.append(np.ravel_multi_index(g[keep].T, shape))
        face_l.append(np.full(int(keep.sum()), k))
        dist_l.append(d[keep])
    cell_ids = np.concatenate(cell_l)
    face_ids = np.concatenate(face_l)
    dist = np.concatenate(dist_l)
    fac = facet[face_ids]
    o = np.lexsort((dist, fac, cell_ids))
    cell_ids, face_ids, dist, fac = cell_ids[o], face_ids[o], dist[o], fac[o]
    first = np.r_[True, (cell_ids[1:] != cell_ids[:-1]) | (fac[1:] != fac[:-1])]
    cell_ids, face_ids, dist = cell_ids[first], face_ids[first], dist[first]
    o = np.lexsort((dist, cell_ids))
    cell_ids, face_ids, dist = cell_ids[o], face_ids[o], dist[o]
    start = np.r_[True, cell_ids[1:] != cell_ids[:-1]]
    group = np.cumsum(start) - 1
    keep = dist <= dist[start][group] + 2.0 * half_diag + 1e-12
    cell_ids, face_ids = cell_ids[keep], face_ids[keep]
    start = np.r_[True, cell_ids[1:] != cell_ids[:-1]]
    first_idx = np.flatnonzero(start)
    rows = np.full(int(np.prod(shape)), -1, dtype=np.int32)
    rows[cell_ids[first_idx]] = np.arange(first_idx.size, dtype=np.int32)
    return FaceGrid(
        planes=planes,
        origin=origin,
        cell=h,
        shape=shape,  # type: ignore[arg-type]
        rows=rows,
        starts=np.r_[first_idx, cell_ids.size].astype(np.int64),
        faces=face_ids.astype(np.int32),
        band=band,
    )


def _slot_distances(grid: FaceGrid, mesh: trimesh.Trimesh) -> FloatArray:
    """Distance [m] of each candidate slot's voxel centre to its face."""
    from perception.estimation.registration.facegrid import (
        _face_table,
        _triangle_distances,
        _unit_normals,
    )

    tris = np.asarray(mesh.triangles, dtype=np.float64)
    table = _face_table(tris, _unit_normals(tris)[0], grid.band)
    cells = np.repeat(np.flatnonzero(grid.rows >= 0), np.diff(grid.starts))
    centre = grid.origin + (np.stack(np.unravel_index(cells, grid.shape), axis=1) + 0.5) * grid.cell
    return _triangle_distances(np.ascontiguousarray(centre.T), table[:, grid.faces])[0]


def _assert_equivalent(new: FaceGrid, ref: FaceGrid, mesh: trimesh.Trimesh, seed: int) -> None:
    """Same voxels, same candidates per voxel and the same ``nearest`` answers, up to how exact
    ties are broken.

    The reference took its distances from BLAS matrix-vector products, whose rounding depends on
    the CPU kernel and on each row's place in the product; so among candidates equidistant from a
    voxel centre (a box's faces meeting at an edge, the two triangles of a square facet) its order
    and its choice of a facet's face were set by that rounding, not by the geometry. Here each
    slot's face must be as near to the voxel centre (1e-12 m) as the reference's, with the same
    facets per voxel, and ``nearest`` must agree exactly except on the few points where such a
    tie decides.
    """
    assert new.shape == ref.shape and new.cell == ref.cell and new.band == ref.band
    np.testing.assert_array_equal(new.origin, ref.origin)
    np.testing.assert_array_equal(new.planes, ref.planes)
    np.testing.assert_array_equal(new.rows, ref.rows)
    np.testing.assert_array_equal(new.starts, ref.starts)
    np.testing.assert_allclose(
        _slot_distances(new, mesh), _slot_distances(ref, mesh), rtol=0, atol=1e-12
    )
    from perception.estimation.registration.facegrid import _facets

    facet = _facets(mesh)[1]
    row = np.repeat(np.arange(new.starts.size - 1), np.diff(new.starts))
    np.testing.assert_array_equal(
        np.sort(row * (facet.max() + 1) + facet[new.faces]),
        np.sort(row * (facet.max() + 1) + facet[ref.faces]),
    )
    assert np.mean(new.faces != ref.faces) < 0.05

    rng = np.random.default_rng(seed)
    pts, fi = trimesh.sample.sample_surface(mesh, 4000, seed=seed)
    nrm = np.asarray(mesh.face_normals)[fi]
    off = rng.uniform(-1.5, 1.5, (len(pts), 1)) * ref.band
    corner = ref.origin + np.asarray(ref.shape) * ref.cell
    q = np.vstack([
        pts + nrm * off + rng.normal(scale=0.2 * ref.cell, size=pts.shape),
        rng.uniform(ref.origin, corner, (1000, 3)),
    ])
    rays = rng.normal(size=q.shape)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    max_cross = rng.uniform(0.2, 3.0, len(q)) * ref.cell
    calls = ((), (rays, 1.0), (rays, 0.3, True), (rays, 0.3, False), (rays, 0.3, True, max_cross))
    for args in calls:
        got, want = new.nearest(q, *args), ref.nearest(q, *args)
        np.testing.assert_array_equal(got[0], want[0])
        assert want[0].size > 1000
        same = (got[2] == want[2]) & np.all(got[3] == want[3], axis=1)
        same &= (got[1] == want[1]) | (np.isnan(got[1]) & np.isnan(want[1]))
        assert np.mean(same) >= 0.998, f"{np.sum(~same)} of {same.size} answers differ"


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(LIBRARY))
def test_build_matches_the_reference_on_the_library(name: str) -> None:
    mesh = load_target(name).model_mesh
    new, ref = FaceGrid.build(mesh), _reference_build(mesh)
    _assert_equivalent(new, ref, mesh, seed=1)


@pytest.mark.parametrize("kind", SHAPE_KINDS)
@pytest.mark.parametrize("seed", [0, 1])
def test_build_matches_the_reference_on_generated_shapes(kind: str, seed: int) -> None:
    mesh = generate_target(kind, seed).model_mesh
    new, ref = FaceGrid.build(mesh), _reference_build(mesh)
    _assert_equivalent(new, ref, mesh, seed=seed)


@pytest.mark.parametrize(
    "mesh",
    [
        trimesh.creation.icosphere(subdivisions=3, radius=0.7),
        trimesh.creation.box(
            (1.0, 0.4, 0.2),
            transform=trimesh.transformations.random_rotation_matrix(
                np.random.default_rng(4).random(3)
            ),
        ),
        trimesh.creation.cylinder(radius=0.3, height=2.0, sections=40),
    ],
    ids=["icosphere", "tilted_box", "cylinder"],
)
@pytest.mark.parametrize("cells", [None, 17])
def test_build_matches_the_reference_on_curved_and_tilted_meshes(
    mesh: trimesh.Trimesh, cells: int | None
) -> None:
    """Faces not aligned with the voxel axes (rounding in every distance), several per voxel."""
    new, ref = FaceGrid.build(mesh, cells), _reference_build(mesh, cells)
    _assert_equivalent(new, ref, mesh, seed=2)


def test_small_batches_give_the_same_grid(monkeypatch: pytest.MonkeyPatch) -> None:
    """Batching of the voxel-face pairs does not change the result (one face per batch here)."""
    import perception.estimation.registration.facegrid as fg

    mesh = generate_target("cylinder_bus", 3).model_mesh
    ref = FaceGrid.build(mesh)
    monkeypatch.setattr(fg, "_BATCH_PAIRS", 1)
    grid = FaceGrid.build(mesh)
    for name in ("rows", "starts", "faces", "planes", "origin"):
        np.testing.assert_array_equal(getattr(grid, name), getattr(ref, name))


def test_registration_reexports_facegrid() -> None:
    from perception.estimation import facegrid, registration

    assert registration.FaceGrid is FaceGrid and "FaceGrid" in registration.__all__
    assert facegrid.FaceGrid is FaceGrid  # the module's old path


def test_mesh_without_area_is_refused() -> None:
    line = [[0, 0, 0], [1, 0, 0], [2, 0, 0]]
    flat = trimesh.Trimesh(vertices=line, faces=[[0, 1, 2]], process=False)
    with pytest.raises(ValueError, match="non-zero area"):
        FaceGrid.build(flat)
