"""Symmetries of a mesh: the rotations about the body origin that map it onto itself
(:func:`find_symmetries`), from the principal axes of its surface's second moment."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import trimesh
from scipy.optimize import minimize_scalar
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from perception.targets.model import FloatArray


def _area_samples(mesh: trimesh.Trimesh, n: int, rng: np.random.Generator) -> FloatArray:
    """(n, 3) area-uniform surface samples [m] drawn with ``rng``."""
    area = np.asarray(mesh.area_faces, dtype=np.float64)
    face = rng.choice(len(area), size=int(n), p=area / area.sum())
    uv = rng.random((int(n), 2))
    flip = uv.sum(axis=1) > 1.0
    uv[flip] = 1.0 - uv[flip]
    tri = np.asarray(mesh.triangles)[face]
    return tri[:, 0] + uv[:, :1] * (tri[:, 1] - tri[:, 0]) + uv[:, 1:] * (tri[:, 2] - tri[:, 0])


def _surface_second_moment(mesh: trimesh.Trimesh) -> FloatArray:
    """(3, 3) exact area-weighted second moment of the surface about the origin [m^4].

    Per triangle ``int x x^T dA = A / 12 (sum_k v_k v_k^T + s s^T)`` with ``s`` the vertex sum: it
    does not depend on how a surface is triangulated, so a symmetric shape gives symmetric moments.
    """
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    area = np.asarray(mesh.area_faces, dtype=np.float64)
    s = tri.sum(axis=1)
    M = np.einsum("f,fki,fkj->ij", area, tri, tri) + np.einsum("f,fi,fj->ij", area, s, s)
    return M / 12.0


def _axis_rotation(axis: FloatArray, angle: float) -> FloatArray:
    a = np.asarray(axis, dtype=np.float64)
    return Rotation.from_rotvec(a / np.linalg.norm(a) * angle).as_matrix()


def _unique_axes(axes: FloatArray, cos_tol: float = 0.999) -> list[FloatArray]:
    """Distinct unit axes (an axis and its opposite are one), in input order."""
    out: list[FloatArray] = []
    for a in axes:
        n = np.linalg.norm(a)
        if not n > 1e-12:
            continue
        a = a / n
        if all(abs(float(a @ b)) < cos_tol for b in out):
            out.append(a)
    return out


def find_symmetries(
    mesh: trimesh.Trimesh,
    tol_m: float | None = None,
    *,
    n_samples: int = 100_000,
    n_test: int = 2_000,
    max_order: int = 12,
    max_group: int = 60,
    seed: int = 0,
) -> list[FloatArray]:
    """Rotations about the body origin that map a mesh onto itself (identity excluded).

    Candidates come from the principal axes of the surface's second moment about the origin (a
    symmetry leaves it unchanged): with three distinct moments, 180 deg about each principal axis;
    with one distinct axis and an equal pair, rotations by 2 pi / n about the distinct axis
    (n = 2..``max_order``) and 180 deg about axes scanned in the equal pair's plane; with three
    equal moments (cube-like), rotations by 2 pi / n about the principal axes, the directions of
    the farthest vertices and the normals of the largest faces. A candidate is a symmetry when every
    one of ``n_test`` surface samples, rotated, lies within ``tol_m`` of a dense set of surface
    samples. Found rotations are closed under composition (the full group from its generators).

    A mesh that is rotationally symmetric within tolerance about an axis (every order passes, e.g.
    a plain finely tessellated cylinder) reports the ``max_order``-fold rotations, a finite sample
    of its continuous symmetry; a sphere-like mesh stops at ``max_group`` elements.

    Args:
        mesh: triangle mesh [m] in the body frame (origin at the centre of mass).
        tol_m: largest distance [m] of a rotated sample from the surface; default 1 % of the largest
            extent (at least 3 x the sample spacing).
        n_samples: dense surface samples the rotated points are matched against.
        n_test: samples rotated by each candidate.
        max_order: highest n of a 2 pi / n rotation tried.
        max_group: cap on the group size (identity included).
        seed: seed of the private generator of the (deterministic) surface sampling.

    Returns:
        (3, 3) rotation matrices, body frame, sorted by angle; empty for an asymmetric mesh.
    """
    if len(mesh.faces) == 0 or not float(mesh.area) > 0:
        return []
    rng = np.random.default_rng(seed)
    dense = _area_samples(mesh, int(n_samples), rng)
    test = dense[: int(n_test)]
    tree = cKDTree(dense)
    size = float(np.max(mesh.extents))
    spacing = math.sqrt(float(mesh.area) / int(n_samples))
    tol = max(0.01 * size, 3.0 * spacing) if tol_m is None else float(tol_m)
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol_m={tol_m}; expected a finite tolerance > 0 [m]")

    def passes(R: FloatArray) -> bool:
        d, _ = tree.query(test @ R.T, distance_upper_bound=tol)
        return bool(np.all(np.isfinite(d)))

    w, V = np.linalg.eigh(_surface_second_moment(mesh))
    close = np.abs(np.diff(w)) <= 0.01 * w[-1]
    gens: list[FloatArray] = []
    if not close.any():
        gens = [R for k in range(3) if passes(R := _axis_rotation(V[:, k], math.pi))]
    elif close.all():
        verts = np.asarray(mesh.vertices)
        far = verts[np.argsort(-np.linalg.norm(verts, axis=1), kind="stable")[:24]]
        big = np.asarray(mesh.face_normals)[np.argsort(-mesh.area_faces, kind="stable")[:24]]
        for a in _unique_axes(np.vstack([V.T, far, big])):
            gens += [R for n in range(2, max_order + 1)
                     if passes(R := _axis_rotation(a, 2 * math.pi / n))]
    else:
        k = 0 if close[1] else 2  # the distinct eigenvalue
        axis, e1, e2 = V[:, k], V[:, (k + 1) % 3], V[:, (k + 2) % 3]
        orders = [
            n for n in range(2, max_order + 1) if passes(_axis_rotation(axis, 2 * math.pi / n))
        ]
        order = min(math.lcm(*orders), max_order) if orders else 1
        if orders:
            gens.append(_axis_rotation(axis, 2 * math.pi / order))
        gens += _in_plane_half_turn(
            tree, test, np.asarray(mesh.vertices), e1, e2, order, tol, passes
        )
    return _closure(gens, passes, max_group)


def _in_plane_half_turn(
    tree: cKDTree, test: FloatArray, verts: FloatArray, e1: FloatArray, e2: FloatArray,
    order: int, tol: float,
    passes: Callable[[FloatArray], bool],
) -> list[FloatArray]:
    """A 180 deg symmetry about an axis in the plane of ``e1``, ``e2``, or nothing.

    With an ``order``-fold axis normal to the plane, such axes repeat every pi / order, so one scan
    of [0, pi / order) at a step that moves no sample more than tol / 2 finds one if any exists;
    the best is refined on the mean match distance, snapped onto an outermost vertex's direction
    when one is within 1e-3 rad (``verts`` (V, 3) [m]), and then checked.
    """
    r_max = float(np.max(np.linalg.norm(test, axis=1)))
    step = 0.5 * tol / max(r_max, 1e-9)
    thetas = np.arange(0.0, math.pi / order, step)
    sub = test[:400]

    def rot(theta: float) -> FloatArray:
        return _axis_rotation(math.cos(theta) * e1 + math.sin(theta) * e2, math.pi)

    Rs = np.stack([rot(t) for t in thetas])
    d, _ = tree.query(np.einsum("kij,nj->kni", Rs, sub).reshape(-1, 3))
    worst = d.reshape(len(thetas), -1).max(axis=1)
    best = int(np.argmin(worst))
    if worst[best] > 1.5 * tol:
        return []
    res = minimize_scalar(
        lambda t: float(tree.query(test @ rot(t).T)[0].mean()),
        bounds=(thetas[best] - step, thetas[best] + step), method="bounded",
        options={"xatol": 1e-6},
    )
    theta = float(res.x)
    # Sampling leaves ~1e-4 rad of error; a 2-fold axis through a vertex (a plate's corner) is
    # exact, so snap onto an outermost vertex's direction within 1e-3 rad (modulo pi / order).
    u, v = verts @ e1, verts @ e2
    r = np.hypot(u, v)
    outer = np.argsort(-r, kind="stable")[:2_000]
    phi = np.arctan2(v[outer], u[outer])
    period = math.pi / order  # the axes repeat: any of them through a vertex fixes theta
    gap = (phi - theta + 0.5 * period) % period - 0.5 * period
    near = np.abs(gap) < 1e-3
    if near.any():
        theta += float(gap[near][np.argmin(np.abs(gap[near]))])
    R = rot(theta)
    return [R] if passes(R) else []


def _closure(
    gens: list[FloatArray], passes: Callable[[FloatArray], bool], max_group: int
) -> list[FloatArray]:
    """The group generated by ``gens`` (checked element by element), identity excluded, sorted."""
    group = [np.eye(3)]
    frontier = list(gens)
    while frontier and len(group) < max_group:
        R = frontier.pop(0)
        if any(np.linalg.norm(R - G) < 0.1 for G in group) or not passes(R):
            continue
        group.append(R)
        frontier += [g @ R for g in gens]
    rest = group[1:]
    rv = [Rotation.from_matrix(R).as_rotvec() for R in rest]
    key = [(round(float(np.linalg.norm(v)), 6), *np.round(v, 6)) for v in rv]
    return [rest[i] for i in sorted(range(len(rest)), key=lambda i: key[i])]
