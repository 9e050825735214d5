"""The target model: :class:`TargetModel` (mesh, materials, port frame, mass properties, regions
of interest, caches of derived data; pickled without its caches), its per-face
:class:`Material`, the :class:`RegionOfInterest` boxes a scan is steered onto and
:func:`port_frame`."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import trimesh

from perception.geometry import make_T

FloatArray = npt.NDArray[np.float64]


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
