"""The library of procedural targets (:data:`LIBRARY`: cubesat, cygnss, iss_port, hubble, with
their documented envelopes :data:`ENVELOPES_M`) and the building blocks they are assembled from
(boxes, cylinders, frustums, petals; :func:`_assemble` adds up mass properties)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import trimesh

from perception.geometry import make_T
from perception.targets.model import Material, RegionOfInterest, TargetModel, port_frame

#: Documented envelopes of the library targets, x * y * z [m] (tests hold the meshes to 1 cm).
ENVELOPES_M: dict[str, tuple[float, float, float]] = {
    "cubesat": (1.20, 0.63, 0.92),
    "cygnss": (3.55, 1.10, 0.47),
    "iss_port": (8.20, 17.82, 44.00),
    "hubble": (13.45, 19.30, 8.25),
}


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
