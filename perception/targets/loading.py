"""Loading a target: :func:`load_target` (a library name, or a mesh file validated on load:
finite vertices, a plausible size in metres, a docking port on the surface facing out or a
default one with a warning, a simplified model-side mesh when dense, symmetries found)."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import numpy.typing as npt
import trimesh

from perception.targets.library import LIBRARY
from perception.targets.mesh_size import triangle_bound
from perception.targets.model import FloatArray, TargetModel, port_frame
from perception.targets.simplify import _simplify
from perception.targets.symmetry import find_symmetries

_LIBRARY_CACHE: dict[str, TargetModel] = {}
#: Mesh file formats read (trimesh reads archives and 2-D drawings too: an archive is a file whose
#: size does not bound what it unpacks to).
MESH_FORMATS = (".stl", ".obj", ".ply", ".off", ".glb", ".gltf")


def load_target(
    name_or_path: str | Path,
    *,
    scale: float | None = None,
    port: tuple[npt.ArrayLike, npt.ArrayLike] | None = None,
    mass: float | None = None,
    reflectivity: float = 0.5,
    specular: bool = False,
    port_tolerance_m: float = 0.05,
    max_model_faces: int = 20_000,
    max_extent_m: float = 200.0,
    max_file_bytes: int = 256 * 2**20,
    max_file_faces: int = 6_000_000,
) -> TargetModel:
    """Load a library target by name, or a mesh file (STL/OBJ/PLY/OFF/GLB/glTF) through trimesh,
    validated.

    Library targets are built once per process and shared (they are read-only in use); the
    keywords apply to mesh files only. A mesh file is checked before it is used:

    - a format outside :data:`MESH_FORMATS`, a file over ``max_file_bytes``, or one that makes more
      than ``max_file_faces`` triangles (bounded from its text or header, before it is read) is
      refused;
    - non-finite vertex coordinates are refused (checked on the raw file, before trimesh's
      processing would silently drop them);
    - a mesh more than ``max_extent_m`` across is refused when ``scale`` is None or 1.0 (a config's
      default ``scale: 1.0`` counts as not given): CAD exports in millimetres are the usual cause,
      and ``scale=0.001`` is suggested. Any other ``scale`` is taken as deliberate;
    - an explicit ``port`` more than ``port_tolerance_m`` from the surface, or whose axis points
      into the hull (more than 90 deg from the outward normal of the nearest face, or a ray along
      it meets the target again within the target's size), is refused;
    - without ``port``, the port is put where a ray down -z through the centre of the mesh's +z
      bounding face first meets the surface, axis the outward normal there, and a ``UserWarning``
      says where and how far below that face centre it is;
    - a mesh of more than ``max_model_faces`` faces keeps its full resolution for the sensor and
      rendering, and gets a simplified copy for the model-side structures
      (:attr:`TargetModel.model_mesh`), with the simplification's deviation measured, stored and
      warned about.

    ``target.symmetries`` is found with :func:`find_symmetries`. Every refusal is a one-line
    ``ValueError`` that names the file and the problem.

    Args:
        name_or_path: a name in :data:`LIBRARY` or a path to a mesh file.
        scale: uniform scale applied to a file mesh (e.g. 0.001 for millimetres); None means 1.0.
        port: ``(position (3,) [m], axis (3,))`` of the docking port in the file's frame after
            scaling; the axis is the outward approach direction (any non-zero length).
        mass: mass [kg] of a file target (default 100 kg, uniform density).
        reflectivity: uniform reflectivity of a file target.
        specular: uniform specular flag of a file target.
        port_tolerance_m: largest distance [m] of an explicit port from the surface.
        max_model_faces: face count above which the model-side mesh is simplified (the ICP face
            grid costs about 0.3 ms per face to build: 20k faces ~6 s, 200k ~1 min).
        max_file_bytes: largest mesh file read (trimesh holds ~1.2 kB per face while loading;
            256 MiB is ~5M binary-STL faces, ~6 GB).
        max_file_faces: most triangles a file may make, bounded before it is read
            (:func:`~perception.targets.mesh_size.triangle_bound`: an OBJ face line of 8 bytes
            or a glTF node instancing a mesh makes triangles a file size does not bound).
        max_extent_m: largest extent [m] accepted without an explicit scale other than 1.

    Raises:
        FileNotFoundError: a path that does not exist.
        ValueError: an unknown name, an unreadable, empty or degenerate mesh, non-finite vertices,
            zero volume, a size that needs a scale, or a port off the surface or facing inward.
    """
    key = str(name_or_path)
    if key in LIBRARY and not Path(key).suffix:
        if key not in _LIBRARY_CACHE:
            _LIBRARY_CACHE[key] = LIBRARY[key]()
        return _LIBRARY_CACHE[key]
    path = Path(name_or_path)
    if not path.suffix:
        raise ValueError(
            f"unknown target {key!r}; expected one of {sorted(LIBRARY)} or a mesh file path"
        )
    if not path.is_file():
        raise FileNotFoundError(f"target mesh file {path} does not exist")
    if path.suffix.lower() not in MESH_FORMATS:
        raise ValueError(
            f"target mesh file {path}: format {path.suffix!r} is not read; expected one of"
            f" {', '.join(MESH_FORMATS)} (archives are not unpacked)"
        )
    if scale is not None and not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale={scale} for {path}; expected a finite value > 0")
    if not (np.isfinite(port_tolerance_m) and port_tolerance_m > 0):
        raise ValueError(f"port_tolerance_m={port_tolerance_m} for {path}; expected > 0 [m]")
    if int(max_model_faces) < 4:
        raise ValueError(f"max_model_faces={max_model_faces} for {path}; expected >= 4")
    m = float(100.0 if mass is None else mass)
    if not (np.isfinite(m) and m > 0):
        raise ValueError(f"mass={mass} for {path}; expected > 0 [kg]")
    size = path.stat().st_size
    if size > int(max_file_bytes):
        raise ValueError(
            f"target mesh file {path} is {size / 2**20:.0f} MiB, more than max_file_bytes="
            f"{int(max_file_bytes) / 2**20:.0f} MiB; decimate it first (ICP and PAH use at most"
            f" {int(max_model_faces)} faces anyway)"
        )
    bound = triangle_bound(path)
    if bound is not None and bound > int(max_file_faces):
        raise ValueError(
            f"target mesh file {path} makes up to {bound:,} triangles, more than max_file_faces="
            f"{int(max_file_faces):,}; decimate it first (ICP and PAH use at most"
            f" {int(max_model_faces)} faces anyway)"
        )

    mesh = _read_mesh(path)
    mesh.apply_scale(1.0 if scale is None else float(scale))
    _check_extent(path, mesh, scale, max_extent_m)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise ValueError(f"target mesh file {path} has only degenerate (zero-area) triangles")
    # Spread about the least-spread direction [m]: zero for a flat or line-like mesh.
    v = np.asarray(mesh.vertices, dtype=np.float64)
    thinnest = 0.0
    if len(v) >= 4:
        thinnest = math.sqrt(max(float(np.linalg.eigvalsh(np.cov(v.T))[0]), 0.0))
    if np.min(mesh.extents) <= 1e-9 or thinnest <= 1e-9:
        raise ValueError(f"target mesh file {path} has zero volume (flat or degenerate geometry)")
    closed = bool(mesh.is_watertight)
    if closed and mesh.volume < 0:
        mesh.invert()  # an inside-out export: faces wound clockwise seen from outside
    solid = mesh if (closed and mesh.volume > 0) else _hull_solid(v)
    com = np.asarray(solid.center_mass, dtype=np.float64)
    inertia = np.asarray(solid.moment_inertia) * (m / solid.mass)
    mesh.apply_translation(-com)
    if port is None:
        port_T = _default_port(path, mesh, com)
    else:
        port_T = _explicit_port(path, mesh, port, com, float(port_tolerance_m), closed)
    simplified, deviation = None, 0.0
    if len(mesh.faces) > int(max_model_faces):
        simplified, deviation = _simplify(path, mesh, int(max_model_faces))
    target = TargetModel(
        name=path.stem,
        mesh=mesh,
        reflectivity=np.full(len(mesh.faces), float(reflectivity)),
        specular=np.full(len(mesh.faces), bool(specular)),
        T_target_port=port_T,
        mass=m,
        inertia=inertia,
        description=f"mesh file {path.name}",
        simplified_mesh=simplified,
        simplification_deviation_m=deviation,
    )
    target.symmetries = find_symmetries(target.model_mesh)
    return target


# ---------------------------------------------------------------------------------------------
# Mesh-file validation
# ---------------------------------------------------------------------------------------------
def _fmt(v: npt.ArrayLike) -> str:
    """A (3,) vector as ``(x, y, z)``, 4 significant digits at 1e-6 resolution, for one-line
    messages."""
    parts = (f"{round(float(x), 6) + 0.0:.4g}" for x in np.asarray(v).reshape(-1))
    return "(" + ", ".join(parts) + ")"


def _read_mesh(path: Path) -> trimesh.Trimesh:
    """The file's triangles, checked for finite coordinates before trimesh's processing."""
    try:
        raw = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        msg = " ".join(str(exc).split())
        raise ValueError(f"target mesh file {path} could not be read as a mesh: {msg}") from exc
    if not isinstance(raw, trimesh.Trimesh) or len(raw.faces) == 0:
        raise ValueError(f"target mesh file {path} holds no triangles")
    verts = np.asarray(raw.vertices, dtype=np.float64)
    bad = ~np.all(np.isfinite(verts), axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"target mesh file {path} has non-finite vertex coordinates: {int(bad.sum())} of"
            f" {len(verts)} vertices (first: index {first}, {_fmt(verts[first])}); expected finite"
            " numbers"
        )
    faces = np.asarray(raw.faces)
    if faces.min() < 0 or faces.max() >= len(verts):
        raise ValueError(
            f"target mesh file {path} has faces referring to missing vertices (indices"
            f" {int(faces.min())}..{int(faces.max())} of {len(verts)} vertices)"
        )
    # Merge coincident vertices (an STL repeats each one per face): on integer keys at 1e-8 m of
    # resolution, as trimesh's processing does, but ~3x faster on millions of faces.
    keys = np.round(verts * 1e8).astype(np.int64)
    order = np.lexsort(keys.T[::-1])
    new = np.ones(len(order), dtype=bool)
    new[1:] = np.any(keys[order[1:]] != keys[order[:-1]], axis=1)
    inv = np.empty(len(order), dtype=np.int64)
    inv[order] = np.cumsum(new) - 1
    return trimesh.Trimesh(vertices=verts[order[new]], faces=inv[faces], process=False)


def _hull_solid(vertices: FloatArray, max_points: int = 50_000) -> trimesh.Trimesh:
    """Convex hull of (a deterministic subsample of) the vertices: the solid of an open mesh."""
    v = np.asarray(vertices, dtype=np.float64)
    if len(v) > max_points:
        extremes = np.concatenate([np.argmin(v, axis=0), np.argmax(v, axis=0)])
        v = v[np.union1d(np.arange(0, len(v), len(v) // max_points + 1), extremes)]
    return trimesh.convex.convex_hull(v)


def _check_extent(
    path: Path, mesh: trimesh.Trimesh, scale: float | None, max_extent_m: float
) -> None:
    """Refuse an implausibly large mesh unless a scale other than 1 was given on purpose."""
    size = float(np.max(mesh.extents))
    if size <= max_extent_m or (scale is not None and scale != 1.0):
        return
    hint = (
        "it looks like millimetres: pass scale=0.001"
        if 1e-3 * size <= max_extent_m
        else "pass the scale that converts its units to metres"
    )
    raise ValueError(
        f"target mesh file {path} is {size:.4g} m across at scale=1, more than"
        f" max_extent_m={max_extent_m:g} m; {hint} (or raise max_extent_m for a structure truly"
        " that large)"
    )


def _closest_surface_point(
    mesh: trimesh.Trimesh, point: FloatArray
) -> tuple[FloatArray, float, FloatArray]:
    """Exact closest surface point to one point, and the faces that tie for it.

    Triangles whose bounding box is farther than the nearest vertex cannot hold the closest point,
    so only the rest go through trimesh's point-triangle projection (fast on millions of faces).

    Returns:
        closest point (3,) [m], its distance [m], indices of the faces within 1 um of that distance.
    """
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    lower = np.linalg.norm(np.maximum(np.maximum(lo - point, point - hi), 0.0), axis=1)
    upper = float(np.sqrt(np.min(np.sum((tri - point) ** 2, axis=2))))
    cand = np.flatnonzero(lower <= upper + 1e-12)
    q = trimesh.triangles.closest_point(tri[cand], np.repeat(point[None], len(cand), axis=0))
    d = np.linalg.norm(q - point, axis=1)
    best = int(np.argmin(d))
    return q[best], float(d[best]), cand[d <= d[best] + 1e-6]


def _first_hit(
    mesh: trimesh.Trimesh, origin: FloatArray, direction: FloatArray
) -> tuple[float, int]:
    """Distance [m] along a unit ray to its first crossing of the mesh beyond 0.1 mm, and the face
    (inf, -1 when it escapes)."""
    loc, _, tri = mesh.ray.intersects_location([origin], [direction], multiple_hits=True)
    if len(loc) == 0:
        return math.inf, -1
    t = (loc - origin) @ direction
    ok = t > 1e-4
    if not ok.any():
        return math.inf, -1
    k = int(np.flatnonzero(ok)[np.argmin(t[ok])])
    return float(t[k]), int(tri[k])


def _outward_normal(
    mesh: trimesh.Trimesh, q: FloatArray, faces: npt.NDArray[np.int64], closed: bool
) -> FloatArray:
    """Outward unit normal of the surface at ``q`` (mean of the tied faces' normals).

    Winding is trusted on a ``closed`` (watertight) mesh, made positive-volume on load. On an open
    mesh the side from which a ray escapes without crossing the mesh again is taken as outside;
    when both or neither side escapes (a hole across from the port), the side facing away from the
    centre of mass (the body origin).
    """
    n = np.asarray(mesh.face_normals[faces], dtype=np.float64).sum(axis=0)
    if not np.linalg.norm(n) > 1e-9:
        n = np.asarray(mesh.face_normals[faces[0]], dtype=np.float64)
    n = n / np.linalg.norm(n)
    if not closed:
        size = float(np.max(mesh.extents))
        out_fwd = math.isinf(_first_hit(mesh, q + 1e-3 * size * n, n)[0])
        out_back = math.isinf(_first_hit(mesh, q - 1e-3 * size * n, -n)[0])
        if (out_back and not out_fwd) or (out_back == out_fwd and float(n @ q) < 0.0):
            n = -n
    return n


def _default_port(path: Path, mesh: trimesh.Trimesh, com: FloatArray) -> FloatArray:
    """Port where a ray down -z through the centre of the +z bounding face meets the surface (or,
    when it misses, the nearest hit of a grid of such rays), axis the outward normal; warns."""
    lo, hi = mesh.bounds
    top = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2]])
    size = float(np.max(hi - lo))
    where = "where a ray down -z through the centre of the +z bounding face meets the surface"
    t, face = _first_hit(mesh, top + np.array([0.0, 0.0, size]), np.array([0.0, 0.0, -1.0]))
    if face >= 0:
        p = top - np.array([0.0, 0.0, t - size])
    else:
        # A hole under the centre (a frame) or a footprint off the centre: the grid ray nearest it.
        g = np.linspace(0.0, 1.0, 65)
        gx, gy = np.meshgrid(lo[0] + g * (hi[0] - lo[0]), lo[1] + g * (hi[1] - lo[1]))
        origins = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, hi[2] + size)])
        order = np.argsort(np.hypot(origins[:, 0] - top[0], origins[:, 1] - top[1]), kind="stable")
        hit = mesh.ray.intersects_any(origins[order], np.tile([0.0, 0.0, -1.0], (len(order), 1)))
        first = order[int(np.argmax(hit))]
        t, face = _first_hit(mesh, origins[first], np.array([0.0, 0.0, -1.0]))
        p = origins[first] - np.array([0.0, 0.0, t])
        where = ("where a ray down -z meets the surface nearest the centre of the +z bounding face"
                 " (a ray through the centre misses the mesh)")
    n = np.asarray(mesh.face_normals[face], dtype=np.float64)
    n = n if n[2] > 0 else -n  # hit from above: the outward side faces up
    gap = float(np.linalg.norm(top - p))
    warnings.warn(
        f"target mesh file {path}: no port given; put it at {_fmt(p + com)} m (file frame) with"
        f" axis {_fmt(n)}, {where}, {gap:.3f} m from that face centre; pass port=(position, axis)"
        " for the real docking port",
        UserWarning,
        stacklevel=3,
    )
    return port_frame(p, n)


def _explicit_port(
    path: Path,
    mesh: trimesh.Trimesh,
    port: tuple[npt.ArrayLike, npt.ArrayLike],
    com: FloatArray,
    tol_m: float,
    closed: bool,
) -> FloatArray:
    """``T_target_port`` of a user's port, refused when off the surface or facing into the hull."""
    try:
        pos = np.asarray(port[0], dtype=np.float64).reshape(3)
        axis = np.asarray(port[1], dtype=np.float64).reshape(3)
    except (TypeError, ValueError, IndexError) as exc:
        raise ValueError(
            f"target mesh file {path}: port={port!r}; expected (position (3,), axis (3,))"
        ) from exc
    if not np.all(np.isfinite(pos)):
        raise ValueError(f"target mesh file {path}: port position {_fmt(pos)} must be finite")
    norm = float(np.linalg.norm(axis))
    if not (np.all(np.isfinite(axis)) and norm > 1e-9):
        raise ValueError(
            f"target mesh file {path}: port axis {_fmt(axis)} must be finite and non-zero"
        )
    axis = axis / norm
    p = pos - com
    q, dist, faces = _closest_surface_point(mesh, p)
    if dist > tol_m:
        raise ValueError(
            f"target mesh file {path}: port {_fmt(pos)} m is {dist:.3f} m from the surface (nearest"
            f" surface point {_fmt(q + com)} m); expected within port_tolerance_m={tol_m:g} m"
        )
    n = _outward_normal(mesh, q, faces, closed)
    angle = float(np.degrees(np.arccos(np.clip(axis @ n, -1.0, 1.0))))
    if angle > 90.0:
        raise ValueError(
            f"target mesh file {path}: port axis {_fmt(axis)} points into the hull, {angle:.0f} deg"
            f" from the outward surface normal {_fmt(n)} at the port; expected < 90 deg"
        )
    size = float(np.max(mesh.extents))
    t, _ = _first_hit(mesh, q + 1e-3 * axis, axis)
    if t < size:
        raise ValueError(
            f"target mesh file {path}: a ray from the port along its axis {_fmt(axis)} meets the"
            f" target again {t + 1e-3:.3f} m out ({angle:.0f} deg from the surface normal);"
            " expected a clear approach axis"
        )
    if angle > 30.0:
        warnings.warn(
            f"target mesh file {path}: port axis {_fmt(axis)} is {angle:.0f} deg from the surface"
            f" normal {_fmt(n)} at the port",
            UserWarning,
            stacklevel=3,
        )
    return port_frame(p, axis)
