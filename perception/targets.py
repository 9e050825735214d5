"""Target models: mesh + materials + docking port + mass properties, and the procedural library.

A ``TargetModel`` is everything the sensor simulator, the estimators and the dynamics need to know
about the object being approached, expressed in the **target body frame**, whose origin is the
target's centre of mass. The library targets are built procedurally from trimesh primitives so they
need no data files; any STL/OBJ/PLY/GLB mesh can be loaded with :func:`load_target` as well.

Library (envelopes are the axis-aligned extents of the mesh in the body frame, x * y * z [m]):

==========  ======================  =====================================================================
name        envelope [m]            what it is
==========  ======================  =====================================================================
cubesat     1.20 x 0.63 x 0.92      ~1 m small satellite (seed 000 "1 cm / 1 deg on a 1 m target")
cygnss      3.55 x 1.10 x 0.47      seed 003 experiment target: bus + two wings (dark cells on +z)
iss_port    8.20 x 17.82 x 44.00    ISS-like docking area: node, PMA-like port (+y, V-bar), labs, truss
hubble      13.45 x 19.30 x 8.25    Hubble-like 13.2 m x 4.3 m cylinder, two arrays, aft grapple port
==========  ======================  =====================================================================

Every library target carries off-centre features (antennas, boom, port, door, star tracker), so its
pose from a full view is unique; ``target.symmetries`` lists any rotation that maps the mesh onto
itself (empty for the whole library; :func:`find_symmetries` finds none there either).

A mesh file is validated on load (see :func:`load_target`): finite vertices, a plausible size in
metres, a docking port on the surface facing out (or a loud warning where one was put), a simplified
model-side mesh when it is dense, and its symmetries found automatically. Procedurally generated
test spacecraft live in :mod:`perception.shapes`.
"""

from __future__ import annotations

import hashlib
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import trimesh
from scipy.optimize import minimize_scalar
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from perception.geometry import make_T

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "Material",
    "RegionOfInterest",
    "TargetModel",
    "LIBRARY",
    "ENVELOPES_M",
    "load_target",
    "port_frame",
    "find_symmetries",
    "has_embree",
]

#: Documented envelopes of the library targets, x * y * z [m] (tests hold the meshes to 1 cm).
ENVELOPES_M: dict[str, tuple[float, float, float]] = {
    "cubesat": (1.20, 0.63, 0.92),
    "cygnss": (3.55, 1.10, 0.47),
    "iss_port": (8.20, 17.82, 44.00),
    "hubble": (13.45, 19.30, 8.25),
}


def has_embree() -> bool:
    """True when trimesh casts rays with Embree (embreex installed)."""
    return bool(trimesh.ray.has_embree)


@dataclass(frozen=True)
class Material:
    """Surface material of a face.

    Attributes:
        reflectivity: diffuse albedo at the laser wavelength, 0..1.
        specular: mirror-like surface (MLI, polished metal) that returns only near normal incidence.
    """

    reflectivity: float
    specular: bool = False


@dataclass(frozen=True)
class RegionOfInterest:
    """An axis-aligned box in the target body frame that a scan can be steered onto.

    Attributes:
        name: e.g. ``"whole"``, ``"docking_area"``, ``"port"``.
        center: (3,) box centre [m], target frame.
        half_extents: (3,) half sizes [m].
    """

    name: str
    center: tuple[float, float, float]
    half_extents: tuple[float, float, float]

    def corners(self) -> FloatArray:
        """(8, 3) corners of the box [m], target frame."""
        return np.asarray(self.center) + _BOX_SIGNS * np.asarray(self.half_extents)


#: Corner signs of a box, in the order of :meth:`RegionOfInterest.corners`.
_BOX_SIGNS = np.array(
    [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64
)
_BOX_SIGNS.setflags(write=False)


def port_frame(position: npt.ArrayLike, axis: npt.ArrayLike) -> FloatArray:
    """``T_target_port`` from a port position [m] and its outward approach axis (port +z).

    The port x axis is chosen deterministically orthogonal to the approach axis (closest to the
    target x axis, or y when the axis is along x).
    """
    p = np.asarray(position, dtype=np.float64).reshape(3)
    z = np.asarray(axis, dtype=np.float64).reshape(3)
    nz = np.linalg.norm(z)
    if not np.isfinite(nz) or nz < 1e-9 or not np.all(np.isfinite(p)):
        raise ValueError(f"port axis {z} / position {p} must be finite with a non-zero axis")
    z = z / nz
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - z * (ref @ z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.column_stack([x, y, z]), p)


@dataclass(eq=False)
class TargetModel:
    """A target spacecraft in its body frame (origin at the centre of mass).

    Attributes:
        name: library name or file stem.
        mesh: triangle mesh [m], body frame.
        reflectivity: (F,) per-face diffuse reflectivity 0..1.
        specular: (F,) per-face specular flag.
        T_target_port: (4, 4) docking-port frame; its +z is the outward approach axis.
        mass: [kg].
        inertia: (3, 3) inertia tensor about the centre of mass, body axes [kg m^2].
        regions: named regions of interest (always ``whole``, ``docking_area`` and ``port``).
        symmetries: (3, 3) rotations mapping the mesh onto itself (besides identity): found by
            :func:`find_symmetries` for loaded and generated targets, empty for the library.
        description: one line for listings.
        simplified_mesh: a decimated copy of a dense ``mesh`` for the model-side structures (ICP
            face grid, PAH), or None; see :attr:`model_mesh`.
        simplification_deviation_m: largest distance [m] found from the simplified surface to
            ``mesh`` (0 when not simplified).
    """

    name: str
    mesh: trimesh.Trimesh
    reflectivity: FloatArray
    specular: npt.NDArray[np.bool_]
    T_target_port: FloatArray
    mass: float
    inertia: FloatArray
    regions: dict[str, RegionOfInterest] = field(default_factory=dict)
    symmetries: list[FloatArray] = field(default_factory=list)
    description: str = ""
    simplified_mesh: trimesh.Trimesh | None = field(default=None, repr=False)
    simplification_deviation_m: float = 0.0
    cache: dict[Any, Any] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        nf = len(self.mesh.faces)
        self.reflectivity = np.asarray(self.reflectivity, dtype=np.float64).reshape(-1)
        self.specular = np.asarray(self.specular, dtype=bool).reshape(-1)
        if self.reflectivity.shape[0] != nf or self.specular.shape[0] != nf:
            raise ValueError(
                f"target {self.name!r}: {nf} faces but {self.reflectivity.shape[0]} reflectivities"
                f" and {self.specular.shape[0]} specular flags; expected one per face"
            )
        if np.any(~np.isfinite(self.reflectivity)) or np.any(
            (self.reflectivity < 0) | (self.reflectivity > 1)
        ):
            raise ValueError(f"target {self.name!r}: reflectivity must be within [0, 1]")
        if not (np.isfinite(self.mass) and self.mass > 0):
            raise ValueError(f"target {self.name!r}: mass {self.mass} must be > 0 [kg]")
        self.inertia = np.asarray(self.inertia, dtype=np.float64).reshape(3, 3)
        if not np.all(np.linalg.eigvalsh(0.5 * (self.inertia + self.inertia.T)) > 0):
            raise ValueError(f"target {self.name!r}: inertia must be symmetric positive definite")
        if not self.regions:
            self.regions = _default_regions(self.mesh, self.T_target_port)

    # -- geometry -------------------------------------------------------------------------------
    @property
    def extents(self) -> FloatArray:
        """(3,) axis-aligned size [m], body frame."""
        return np.asarray(self.mesh.extents, dtype=np.float64)

    @property
    def bounds(self) -> FloatArray:
        """(2, 3) min and max corners [m], body frame."""
        return np.asarray(self.mesh.bounds, dtype=np.float64)

    @property
    def radius(self) -> float:
        """Radius [m] of the smallest origin-centred sphere holding the mesh."""
        return float(np.linalg.norm(self.mesh.vertices, axis=1).max())

    @property
    def port_position(self) -> FloatArray:
        """(3,) port position [m], body frame."""
        return self.T_target_port[:3, 3].copy()

    @property
    def port_axis(self) -> FloatArray:
        """(3,) unit outward approach axis of the port, body frame."""
        return self.T_target_port[:3, 2].copy()

    @property
    def model_mesh(self) -> trimesh.Trimesh:
        """The mesh the model-side structures are built on (ICP face grid, PAH database).

        The simplified mesh of a dense file target (see :func:`load_target` ``max_model_faces``),
        otherwise :attr:`mesh` itself. The sensor and rendering always cast rays on :attr:`mesh`.
        """
        return self.mesh if self.simplified_mesh is None else self.simplified_mesh

    def model_view(self) -> TargetModel:
        """The target as the model-side structures see it: itself, or for a simplified dense
        target the same target on :attr:`model_mesh` (materials carried over from the nearest
        original face), so that ray casts, face planes and face grids on the model side index
        the same faces. Cached; the sensor keeps casting on the full :attr:`mesh`."""
        if self.simplified_mesh is None:
            return self

        def build() -> TargetModel:
            from scipy.spatial import cKDTree

            simple = self.simplified_mesh
            assert simple is not None
            _, near = cKDTree(np.asarray(self.mesh.triangles_center)).query(
                np.asarray(simple.triangles_center), k=1
            )
            return TargetModel(
                name=self.name, mesh=simple, reflectivity=self.reflectivity[near],
                specular=self.specular[near], T_target_port=self.T_target_port.copy(),
                mass=self.mass, inertia=self.inertia.copy(), regions=dict(self.regions),
                symmetries=list(self.symmetries), description=self.description,
            )

        return self.cached(("model_view",), build)  # type: ignore[no-any-return]

    @property
    def ray(self) -> Any:
        """The mesh's ray intersector (Embree when embreex is installed)."""
        return self.mesh.ray

    @property
    def model_hash(self) -> str:
        """SHA-256 of vertices, faces and materials: identifies the geometry a database was built on."""
        key = ("model_hash",)
        if key not in self.cache:
            h = hashlib.sha256()
            h.update(np.ascontiguousarray(self.mesh.vertices, dtype=np.float64).tobytes())
            h.update(np.ascontiguousarray(self.mesh.faces, dtype=np.int64).tobytes())
            h.update(np.ascontiguousarray(self.reflectivity).tobytes())
            h.update(np.ascontiguousarray(self.specular).tobytes())
            self.cache[key] = h.hexdigest()
        return str(self.cache[key])

    def sample_surface(self, n: int, seed: int = 0) -> tuple[FloatArray, FloatArray]:
        """Area-uniform surface samples with their outward face normals, cached per ``(n, seed)``.

        Args:
            n: number of samples (>= 1).
            seed: seed of the private generator used for the (deterministic) sampling.

        Returns:
            points (n, 3) [m] and unit normals (n, 3), body frame. Read-only arrays.
        """
        if int(n) < 1:
            raise ValueError(f"sample_surface n={n}; expected >= 1")
        key = ("surface", int(n), int(seed))
        if key not in self.cache:
            rng = np.random.default_rng(seed)
            area = self.mesh.area_faces
            face = rng.choice(len(area), size=int(n), p=area / area.sum())
            uv = rng.random((int(n), 2))
            flip = uv.sum(axis=1) > 1.0
            uv[flip] = 1.0 - uv[flip]
            tri = self.mesh.triangles[face]
            pts = tri[:, 0] + uv[:, :1] * (tri[:, 1] - tri[:, 0]) + uv[:, 1:] * (tri[:, 2] - tri[:, 0])
            nrm = np.asarray(self.mesh.face_normals[face], dtype=np.float64)
            pts.setflags(write=False)
            nrm.setflags(write=False)
            self.cache[key] = (pts, nrm)
        return self.cache[key]

    def cached(self, key: Any, build: Callable[[], Any]) -> Any:
        """Return ``cache[key]``, building it once with ``build()``: derived data lives with its target."""
        if key not in self.cache:
            self.cache[key] = build()
        return self.cache[key]

    def summary(self) -> dict[str, Any]:
        """One row for listings: name, extents, faces, port, mass."""
        return {
            "name": self.name,
            "extents_m": tuple(float(v) for v in self.extents),
            "faces": len(self.mesh.faces),
            "port_m": tuple(float(v) for v in self.port_position),
            "port_axis": tuple(float(v) for v in self.port_axis),
            "mass_kg": float(self.mass),
            "watertight": bool(self.mesh.is_watertight),
            "description": self.description,
        }

    def __getstate__(self) -> dict[str, Any]:
        # Caches (KD-trees, Embree scenes) are rebuilt per process rather than pickled.
        state = self.__dict__.copy()
        state["cache"] = {}
        for key in ("mesh", "simplified_mesh"):
            mesh = state.get(key)
            if mesh is not None:
                state[key] = (np.asarray(mesh.vertices), np.asarray(mesh.faces))
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        for key in ("mesh", "simplified_mesh"):
            if state.get(key) is not None:
                v, f = state[key]
                state[key] = trimesh.Trimesh(vertices=v, faces=f, process=False)
        state.setdefault("simplified_mesh", None)
        state.setdefault("simplification_deviation_m", 0.0)
        self.__dict__.update(state)


# ---------------------------------------------------------------------------------------------
# Symmetries
# ---------------------------------------------------------------------------------------------
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


# ---------------------------------------------------------------------------------------------
# Building blocks
# ---------------------------------------------------------------------------------------------
@dataclass
class _Part:
    mesh: trimesh.Trimesh
    mass: float
    material: Material
    # Optional material for faces whose normal points along +normal_dir (e.g. solar cells).
    face_material: tuple[npt.NDArray[np.float64], Material] | None = None


def _box(extents: tuple[float, float, float], center: tuple[float, float, float]) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=make_T(None, center))


def _cylinder(
    radius: float, length: float, center: tuple[float, float, float], axis: str, sections: int = 32
) -> trimesh.Trimesh:
    R = {"x": [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], "y": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
         "z": np.eye(3)}[axis]
    # Rotating z onto the requested axis; vertices at k*2pi/32 keep the diameter exact on both
    # transverse axes.
    return trimesh.creation.cylinder(
        radius=radius, height=length, sections=sections, transform=make_T(np.asarray(R).T, center)
    )


def _frustum(
    r0: float, r1: float, start: float, end: float, axis: str, offset: tuple[float, float] = (0, 0),
    sections: int = 32,
) -> trimesh.Trimesh:
    """A closed conical frustum along ``axis`` from coordinate ``start`` (radius r0) to ``end`` (r1)."""
    ang = np.linspace(0.0, 2 * np.pi, sections, endpoint=False)
    ring = np.column_stack([np.cos(ang), np.sin(ang)])
    a = np.column_stack([ring * r0, np.full(sections, start)])
    b = np.column_stack([ring * r1, np.full(sections, end)])
    verts = np.vstack([a, b, [[0, 0, start], [0, 0, end]]])
    i = np.arange(sections)
    j = (i + 1) % sections
    side1 = np.column_stack([i, j, sections + j])
    side2 = np.column_stack([i, sections + j, sections + i])
    cap_a = np.column_stack([np.full(sections, 2 * sections), j, i])
    cap_b = np.column_stack([np.full(sections, 2 * sections + 1), sections + i, sections + j])
    faces = np.vstack([side1, side2, cap_a, cap_b])
    mesh = trimesh.Trimesh(verts, faces, process=True)
    if start > end:
        mesh.invert()
    if mesh.volume < 0:
        mesh.invert()
    # Map local (u, v, w) with w along the axis into target coordinates.
    local = mesh.vertices.copy()
    out = np.zeros_like(local)
    axis_idx = "xyz".index(axis)
    others = [k for k in range(3) if k != axis_idx]
    out[:, axis_idx] = local[:, 2]
    out[:, others[0]] = local[:, 0] + offset[0]
    out[:, others[1]] = local[:, 1] + offset[1]
    m = trimesh.Trimesh(out, mesh.faces, process=True)
    if m.volume < 0:
        m.invert()
    return m


def _petal(
    angle_deg: float, radius: float, base: float, height: float, depth: float, plane: float
) -> trimesh.Trimesh:
    """A docking-mechanism guide petal on a hatch facing +y: a triangular prism standing on ``plane``.

    The triangle lies in the tangential-axial plane (``base`` wide on the hatch, apex ``height``
    above it) and is extruded ``depth`` along the radius, centred ``radius`` from the axis at
    ``angle_deg`` in the x-z plane. Its two flanks slope about the radial direction, so their
    normals have a tangential component: a range sensor looking down the port axis measures roll
    about that axis from the points on them (a box seen end-on shows roll only at its edges).
    """
    a = np.radians(angle_deg)
    u = np.array([np.cos(a), 0.0, np.sin(a)])  # radial
    v = np.array([-np.sin(a), 0.0, np.cos(a)])  # tangential
    y = np.array([0.0, 1.0, 0.0])
    tri = [(-0.5 * base, 0.0), (0.5 * base, 0.0), (0.0, height)]
    c = radius * u + plane * y
    verts = [c + s * 0.5 * depth * u + tv * v + ty * y for s in (-1.0, 1.0) for tv, ty in tri]
    return trimesh.convex.convex_hull(np.array(verts))


def _assemble(
    name: str,
    parts: list[_Part],
    port_position: tuple[float, float, float],
    port_axis: tuple[float, float, float],
    description: str,
    regions: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] | None = None,
) -> TargetModel:
    """Concatenate parts, assign per-face materials, compute mass properties, move origin to CoM."""
    meshes = [p.mesh for p in parts]
    refl, spec = [], []
    total_mass = sum(p.mass for p in parts)
    com = sum(p.mass * np.asarray(p.mesh.center_mass) for p in parts) / total_mass
    inertia = np.zeros((3, 3))
    for p in parts:
        m = p.mesh
        local = np.asarray(m.moment_inertia) * (p.mass / m.mass)  # trimesh uses density 1
        d = np.asarray(m.center_mass) - com
        inertia += local + p.mass * (d @ d * np.eye(3) - np.outer(d, d))
        r = np.full(len(m.faces), p.material.reflectivity)
        s = np.full(len(m.faces), p.material.specular)
        if p.face_material is not None:
            direction, mat = p.face_material
            sel = m.face_normals @ np.asarray(direction) > 0.5
            r[sel] = mat.reflectivity
            s[sel] = mat.specular
        refl.append(r)
        spec.append(s)
    mesh = trimesh.util.concatenate(meshes)
    mesh.apply_translation(-com)
    T_port = port_frame(np.asarray(port_position) - com, port_axis)
    roi = None
    if regions is not None:
        roi = {
            k: RegionOfInterest(k, tuple(np.asarray(c) - com), tuple(h))  # type: ignore[arg-type]
            for k, (c, h) in regions.items()
        }
    target = TargetModel(
        name=name,
        mesh=mesh,
        reflectivity=np.concatenate(refl),
        specular=np.concatenate(spec),
        T_target_port=T_port,
        mass=float(total_mass),
        inertia=0.5 * (inertia + inertia.T),
        regions=roi or {},
        description=description,
    )
    return target


def _default_regions(mesh: trimesh.Trimesh, T_target_port: FloatArray) -> dict[str, RegionOfInterest]:
    lo, hi = mesh.bounds
    size = float(np.max(hi - lo))
    port = T_target_port[:3, 3]
    whole = RegionOfInterest("whole", tuple((lo + hi) / 2), tuple((hi - lo) / 2))
    d_area = max(0.25 * size, 0.3)
    docking = RegionOfInterest("docking_area", tuple(port), (d_area, d_area, d_area))
    d_port = max(0.06 * size, 0.15)
    port_roi = RegionOfInterest("port", tuple(port), (d_port, d_port, d_port))
    return {"whole": whole, "docking_area": docking, "port": port_roi}


# Common materials (reflectivity at ~1.5 um, order of magnitude).
WHITE_PAINT = Material(0.80)
MLI = Material(0.45)
SOLAR_CELL = Material(0.08)
PANEL_BACK = Material(0.60)
ALUMINIUM = Material(0.55)
POLISHED = Material(0.90, specular=True)
TRUSS = Material(0.40)


def _cubesat() -> TargetModel:
    parts = [
        _Part(_box((0.60, 0.60, 0.80), (0, 0, 0)), 60.0, MLI),
        # Docking interface ring on +z (the port), diffuse aluminium.
        _Part(_cylinder(0.12, 0.06, (0, 0, 0.43), "z"), 2.0, ALUMINIUM),
        # One deployed wing on +x, cells on +z.
        _Part(_box((0.40, 0.55, 0.02), (0.50, 0, 0.10)), 3.0, PANEL_BACK,
              (np.array([0, 0, 1.0]), SOLAR_CELL)),
        # Whip antenna on -x, offset in +y and -z.
        _Part(_box((0.20, 0.02, 0.02), (-0.40, 0.20, -0.30)), 0.2, ALUMINIUM),
        # Patch antenna on -y.
        _Part(_box((0.12, 0.03, 0.12), (0.10, -0.315, 0.20)), 0.3, WHITE_PAINT),
        # Polished thruster nozzle on -z, off centre.
        _Part(_frustum(0.03, 0.05, -0.40, -0.46, "z", offset=(0.15, -0.15)), 0.5, POLISHED),
    ]
    return _assemble(
        "cubesat", parts, (0, 0, 0.46), (0, 0, 1),
        "1 m-class small satellite, port ring on +z, one wing on +x",
    )


def _cygnss() -> TargetModel:
    parts = [
        _Part(_box((0.85, 0.86, 0.40), (0, 0, 0)), 20.0, MLI),
        # Two wings along x, 1.35 m each from the bus sides; dark cells on +z, bright backs.
        _Part(_box((1.35, 0.50, 0.02), (0.425 + 0.675, 0, 0)), 2.0, PANEL_BACK,
              (np.array([0, 0, 1.0]), SOLAR_CELL)),
        _Part(_box((1.35, 0.50, 0.02), (-0.425 - 0.675, 0, 0)), 2.0, PANEL_BACK,
              (np.array([0, 0, 1.0]), SOLAR_CELL)),
        # Antenna boom on +y.
        _Part(_box((0.10, 0.24, 0.10), (0.20, 0.43 + 0.12, 0.0)), 0.5, ALUMINIUM),
        # Docking port ring on +z, centred on the bus.
        _Part(_cylinder(0.10, 0.07, (0, 0, 0.235), "z"), 1.0, ALUMINIUM),
        # Star tracker box, off centre on +z.
        _Part(_box((0.12, 0.10, 0.05), (0.25, 0.25, 0.225)), 0.4, WHITE_PAINT),
    ]
    return _assemble(
        "cygnss", parts, (0, 0, 0.27), (0, 0, 1),
        "seed-003 CYGNSS-like microsatellite: bus, two wings, boom on +y, port on +z",
        # The wings' +z faces are dark cells that return little at TOF ranges: close in, the
        # docking area is the bus face around the port (its edges fix the roll about the port
        # axis), not a box that spends most of the scan on the wings.
        regions={
            "whole": ((0.0, 0.12, 0.035), (1.78, 0.56, 0.24)),
            "docking_area": ((0.0, 0.0, 0.05), (0.46, 0.46, 0.25)),
            "port": ((0.0, 0.0, 0.235), (0.2, 0.2, 0.1)),
        },
    )


def _iss_port() -> TargetModel:
    parts = [
        # Node along y (V-bar) with the PMA-like conical adapter forward (+y).
        _Part(_cylinder(2.2, 7.2, (0, 0, 0), "y"), 14_000.0, WHITE_PAINT),
        _Part(_frustum(1.3, 0.9, 3.6, 5.4, "y"), 1_500.0, ALUMINIUM),
        # Lab module aft along -y.
        _Part(_cylinder(2.2, 8.5, (0, -3.6 - 4.25, 0), "y"), 14_500.0, WHITE_PAINT),
        # Two side labs: a short one on +z and a longer one on -z.
        _Part(_cylinder(2.2, 6.5, (0, 0, 2.2 + 3.25), "z"), 10_000.0, WHITE_PAINT),
        _Part(_cylinder(2.2, 11.0, (0, 0, -2.2 - 5.5), "z"), 15_000.0, WHITE_PAINT),
        # Truss across, above (zenith, +x) the aft lab.
        _Part(_box((2.0, 2.0, 44.0), (5.0, -8.0, 0)), 100_000.0, TRUSS),
        # Strut joining truss and lab.
        _Part(_box((1.6, 1.0, 1.0), (3.0, -8.0, 0)), 500.0, TRUSS),
        # Close-range features on the hatch (y = 5.4): three guide petals at 120 deg and an
        # off-centre centreline docking target standoff, so the last metres (where only the
        # port fills the field of view) keep all six degrees of freedom observable. The petals
        # are wedges whose sloping flanks face along the circumference, like a mechanism's roll
        # guides: looking down the port axis, their points measure roll directly (0.25 m cubes
        # did so only at their edges: roll 0.5 deg RMS at 2-4 m against a 0.07 deg bound).
        *[
            _Part(_petal(a, 0.75, 0.25, 0.25, 0.25, 5.4), 30.0, ALUMINIUM)
            for a in (90.0, 210.0, 330.0)
        ],
        # (0.75 m off the axis: a chaser hull sphere of 0.5 m centred 0.6 m behind the docking
        # plane clears it by 8 cm at contact with the envelope's 0.10 m lateral offset; at 0.55 m
        # it struck the standoff from 5 cm of offset, a "collision" inside the envelope.)
        _Part(_box((0.12, 0.30, 0.12), (0.75, 5.55, 0.25)), 5.0, WHITE_PAINT),
        _Part(_box((0.26, 0.02, 0.26), (0.75, 5.71, 0.25)), 2.0, WHITE_PAINT),
    ]
    return _assemble(
        "iss_port", parts, (0, 5.4, 0), (0, 1, 0),
        "ISS-like docking area: node + PMA-like port facing +y (V-bar), labs, truss",
        regions={
            "whole": ((2.0, -3.35, 0.0), (4.2, 8.8, 22.0)),
            "docking_area": ((0.0, 3.0, 0.0), (2.6, 2.6, 2.6)),
            "port": ((0.0, 5.45, 0.0), (1.0, 0.3, 1.0)),
        },
    )


def _hubble() -> TargetModel:
    parts = [
        _Part(_cylinder(2.15, 13.2, (0, 0, 0), "x"), 9_000.0, MLI),
        # Two arrays on masts along +-y, 2.45 m wide, cells on +z.
        _Part(_box((2.45, 7.1, 0.02), (1.0, 2.55 + 3.55, 0)), 300.0, PANEL_BACK,
              (np.array([0, 0, 1.0]), SOLAR_CELL)),
        _Part(_box((2.45, 7.1, 0.02), (1.0, -2.55 - 3.55, 0)), 300.0, PANEL_BACK,
              (np.array([0, 0, 1.0]), SOLAR_CELL)),
        _Part(_box((0.2, 0.4, 0.2), (1.0, 2.35, 0)), 20.0, ALUMINIUM),
        _Part(_box((0.2, 0.4, 0.2), (1.0, -2.35, 0)), 20.0, ALUMINIUM),
        # Open aperture door at the forward (+x) end, standing up on +z.
        _Part(_box((0.10, 3.0, 2.95), (6.65, 0, 2.15 + 1.475)), 150.0, MLI),
        # High-gain antenna booms, one on +z (forward), one on -z (aft): not mirror images.
        _Part(_box((0.3, 0.3, 1.6), (2.5, 0, 2.15 + 0.8)), 30.0, ALUMINIUM),
        _Part(_box((0.3, 0.3, 1.0), (-1.5, 0.8, -2.15 - 0.5)), 30.0, ALUMINIUM),
        # Aft bulkhead grapple / docking fixture (the port), off the axis.
        _Part(_box((0.15, 0.6, 0.6), (-6.6 - 0.075, 0.6, 0.6)), 40.0, ALUMINIUM),
    ]
    return _assemble(
        "hubble", parts, (-6.75, 0.6, 0.6), (-1, 0, 0),
        "Hubble-like 13.2 m x 4.3 m telescope: two arrays, open door on +x, aft grapple port (-x)",
    )


#: Library builders by name.
LIBRARY: dict[str, Callable[[], TargetModel]] = {
    "cubesat": _cubesat,
    "cygnss": _cygnss,
    "iss_port": _iss_port,
    "hubble": _hubble,
}

_LIBRARY_CACHE: dict[str, TargetModel] = {}


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
) -> TargetModel:
    """Load a library target by name, or a mesh file (STL/OBJ/PLY/GLB) through trimesh, validated.

    Library targets are built once per process and shared (they are read-only in use); the
    keywords apply to mesh files only. A mesh file is checked before it is used:

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


# ---------------------------------------------------------------------------------------------
# Dense meshes
# ---------------------------------------------------------------------------------------------
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
