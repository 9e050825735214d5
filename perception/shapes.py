"""Procedurally generated test spacecraft: shapes users bring, not those the library was tuned on.

Every generated target is a concatenation of closed trimesh primitives (the library's
:func:`perception.targets._assemble`), origin at its centre of mass, 1-6 m across, with its docking
port on the surface of a flat face (axis the outward face normal) and diffuse materials of
reflectivity 0.3-0.85. ``target.symmetries`` is found by :func:`perception.targets.find_symmetries`.

==================  ==============================================================================
kind                what it is
==================  ==============================================================================
assembly            box bus 0.8-2.2 m with 1-5 random boxes, cylinders, plates and booms on its
                    side and bottom faces; port on the bus's +z face
flat_face           box bus 1.5-3.5 m, plain +z docking face, port centred or off-centre; an
                    off-centre antenna and maybe a solar panel elsewhere (no symmetry)
symmetric_plate     square plate 1.5-2.5 m x 0.2-0.35 m, port at the centre of +z (dihedral group of
                    order 8: 7 symmetries besides identity)
thin_frame          square frame of four 0.05-0.1 m beams, 1.5-3 m, with a small docking plate on
                    top of one beam carrying the port
cylinder_bus        cylinder bus along z, port on its +z end face, a boom or a panel on a mast
boxes_and_booms     box bus with 1-3 smaller boxes and one long boom (2-3 m)
==================  ==============================================================================

The docking face is always +z of the bus and nothing is mounted on it except the port, so the
port is visible along its axis from outside. Same kind and seed give a bitwise-identical mesh.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.typing as npt
import trimesh

from perception.targets import (
    Material,
    TargetModel,
    _assemble,
    _box,
    _cylinder,
    _Part,
    find_symmetries,
)

FloatArray = npt.NDArray[np.float64]
Vec3 = tuple[float, float, float]

__all__ = ["SHAPE_KINDS", "generate_target", "save_generated"]

#: Depth [m] by which an appendage is sunk into the face it stands on (no coplanar contact faces).
_EMBED_M = 0.01


def _material(rng: np.random.Generator) -> Material:
    return Material(float(rng.uniform(0.3, 0.85)))


def _part(mesh: trimesh.Trimesh, rng: np.random.Generator, density: tuple[float, float]) -> _Part:
    """A part of uniform density drawn from ``density`` [kg/m^3] and a random diffuse material."""
    rho = float(rng.uniform(*density))
    return _Part(mesh, rho * float(mesh.volume), _material(rng))


def _v3(a: npt.ArrayLike) -> Vec3:
    x = np.asarray(a, dtype=np.float64).reshape(3)
    return (float(x[0]), float(x[1]), float(x[2]))


def _mounted_box(
    half: FloatArray, axis: int, sign: int, size: FloatArray, uv: tuple[float, float]
) -> trimesh.Trimesh:
    """A box standing on face ``sign * axis`` of a bus of half extents ``half`` [m], centred at the
    bus origin.

    Args:
        half: (3,) bus half extents [m].
        axis: index of the face normal (0, 1, 2).
        sign: +1 or -1.
        size: (3,) box extents [m]; along ``axis`` it is the height above the face.
        uv: position of the box centre on the face, as fractions (-1..1) of the room left on the
            two tangent axes (in increasing axis order), so the footprint stays on the face.
    """
    size = np.asarray(size, dtype=np.float64).copy()
    center = np.zeros(3)
    tangents = [k for k in range(3) if k != axis]
    for k, f in zip(tangents, uv, strict=True):
        size[k] = min(size[k], 1.8 * half[k])  # footprint no wider than the face
        center[k] = f * (half[k] - 0.5 * size[k])
    center[axis] = sign * (half[axis] + 0.5 * size[axis] - _EMBED_M)
    return _box(_v3(size), _v3(center))


def _appendage(
    rng: np.random.Generator, half: FloatArray, axis: int, sign: int, kind: str,
    uv: tuple[float, float] | None = None,
) -> trimesh.Trimesh:
    """A box, cylinder, plate or boom on face ``sign * axis`` of a box bus (half extents [m])."""
    if uv is None:
        uv = (float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)))
    tangents = [k for k in range(3) if k != axis]
    if kind == "cylinder":
        r = float(min(rng.uniform(0.1, 0.4), 0.9 * min(half[k] for k in tangents)))
        length = float(rng.uniform(0.2, 1.0))
        center = np.zeros(3)
        for k, f in zip(tangents, uv, strict=True):
            center[k] = f * (half[k] - r)
        center[axis] = sign * (half[axis] + 0.5 * length - _EMBED_M)
        return _cylinder(r, length, _v3(center), "xyz"[axis])
    size = np.zeros(3)
    if kind == "box":
        size[:] = rng.uniform(0.2, 0.8, 3)
    elif kind == "plate":  # a solar panel standing out of the face, thin across one tangent
        size[axis] = rng.uniform(0.8, 1.6)
        size[tangents[0]] = rng.uniform(0.5, 1.2)
        size[tangents[1]] = rng.uniform(0.03, 0.06)
        if rng.random() < 0.5:
            size[tangents] = size[tangents[::-1]]
    elif kind == "boom":
        size[axis] = rng.uniform(0.8, 1.8)
        size[tangents] = rng.uniform(0.05, 0.1)
    else:
        raise ValueError(f"appendage kind {kind!r}; expected box, cylinder, plate or boom")
    return _mounted_box(half, axis, sign, size, uv)


def _off_centre(rng: np.random.Generator) -> tuple[float, float]:
    """Face fractions at least 0.4 from the centre on both tangents (breaks every symmetry)."""
    return (float(rng.choice([-1, 1]) * rng.uniform(0.4, 0.9)),
            float(rng.choice([-1, 1]) * rng.uniform(0.4, 0.9)))


def _port_on_top(rng: np.random.Generator, half: FloatArray, spread: float) -> Vec3:
    """A point on the bus's +z face, within ``spread`` x the half extents of its centre [m]."""
    xy = rng.uniform(-spread, spread, 2) * half[:2]
    return (float(xy[0]), float(xy[1]), float(half[2]))


_BUS_DENSITY = (150.0, 400.0)
_APPENDAGE_DENSITY = (50.0, 300.0)
#: Faces of a box bus an appendage may stand on: +-x, +-y, -z (never the +z docking face).
_MOUNT_FACES = ((0, 1), (0, -1), (1, 1), (1, -1), (2, -1))


def _assembly(rng: np.random.Generator) -> tuple[list[_Part], Vec3, Vec3]:
    half = 0.5 * rng.uniform(0.8, 2.2, 3)
    parts = [_part(_box(_v3(2 * half), (0, 0, 0)), rng, _BUS_DENSITY)]
    # The first appendage is an off-centre boom on a side face: no rotation maps it onto itself.
    axis, sign = _MOUNT_FACES[int(rng.integers(4))]
    parts.append(_part(_appendage(rng, half, axis, sign, "boom", _off_centre(rng)), rng,
                       _APPENDAGE_DENSITY))
    for _ in range(int(rng.integers(0, 5))):
        axis, sign = _MOUNT_FACES[int(rng.integers(len(_MOUNT_FACES)))]
        kind = str(rng.choice(["box", "cylinder", "plate", "boom"]))
        parts.append(_part(_appendage(rng, half, axis, sign, kind), rng, _APPENDAGE_DENSITY))
    return parts, _port_on_top(rng, half, 0.5), (0.0, 0.0, 1.0)


def _flat_face(rng: np.random.Generator) -> tuple[list[_Part], Vec3, Vec3]:
    ext = np.array([rng.uniform(1.5, 3.5), rng.uniform(1.5, 3.5), rng.uniform(1.0, 2.5)])
    half = 0.5 * ext
    parts = [_part(_box(_v3(ext), (0, 0, 0)), rng, _BUS_DENSITY)]
    # An antenna: a thin short mast off-centre on a side face.
    axis, sign = _MOUNT_FACES[int(rng.integers(4))]
    size = np.zeros(3)
    size[axis] = rng.uniform(0.4, 1.0)
    size[[k for k in range(3) if k != axis]] = rng.uniform(0.04, 0.08)
    parts.append(_part(_mounted_box(half, axis, sign, size, _off_centre(rng)), rng,
                       _APPENDAGE_DENSITY))
    if rng.random() < 0.5:  # a solar panel on a face of the other horizontal axis
        p_axis = 1 - axis if axis < 2 else 0
        size = np.zeros(3)
        size[p_axis] = rng.uniform(0.8, 1.2)
        size[1 - p_axis] = rng.uniform(0.6, 1.0)
        size[2] = 0.03
        uv = (float(rng.uniform(-0.5, 0.5)), float(rng.uniform(-0.5, 0.5)))
        parts.append(_part(_mounted_box(half, p_axis, int(rng.choice([-1, 1])), size, uv), rng,
                           _APPENDAGE_DENSITY))
    port = (0.0, 0.0, float(half[2])) if rng.random() < 0.5 else _port_on_top(rng, half, 0.6)
    return parts, port, (0.0, 0.0, 1.0)


def _symmetric_plate(rng: np.random.Generator) -> tuple[list[_Part], Vec3, Vec3]:
    a = float(rng.uniform(1.5, 2.5))
    t = float(rng.uniform(0.2, 0.35))
    parts = [_part(_box((a, a, t), (0, 0, 0)), rng, _BUS_DENSITY)]
    return parts, (0.0, 0.0, 0.5 * t), (0.0, 0.0, 1.0)


def _thin_frame(rng: np.random.Generator) -> tuple[list[_Part], Vec3, Vec3]:
    L = float(rng.uniform(1.5, 3.0))
    w = float(rng.uniform(0.05, 0.1))
    c = 0.5 * (L - w)
    parts = [
        _part(_box((L, w, w), (0, c, 0)), rng, _BUS_DENSITY),
        _part(_box((L, w, w), (0, -c, 0)), rng, _BUS_DENSITY),
        _part(_box((w, L - 2 * w, w), (c, 0, 0)), rng, _BUS_DENSITY),
        _part(_box((w, L - 2 * w, w), (-c, 0, 0)), rng, _BUS_DENSITY),
    ]
    p = float(rng.uniform(0.25, 0.4))
    pt = float(rng.uniform(0.03, 0.05))
    x = float(rng.uniform(-0.3, 0.3) * L)
    z0 = 0.5 * w - 0.5 * _EMBED_M
    parts.append(_part(_box((p, p, pt), (x, c, z0 + 0.5 * pt)), rng, _APPENDAGE_DENSITY))
    return parts, (x, c, z0 + pt), (0.0, 0.0, 1.0)


def _cylinder_bus(rng: np.random.Generator) -> tuple[list[_Part], Vec3, Vec3]:
    r = float(rng.uniform(0.5, 1.1))
    length = float(rng.uniform(1.2, 3.0))
    parts = [_part(_cylinder(r, length, (0, 0, 0), "z"), rng, _BUS_DENSITY)]
    # A boom or a panel on a mast, along +-x or +-y, at least 0.2 length off the mid-plane.
    axis = int(rng.integers(2))
    sign = int(rng.choice([-1, 1]))
    z = float(rng.choice([-1, 1]) * rng.uniform(0.2, 0.4) * length)
    start = 0.95 * r  # sunk into the faceted side
    if rng.random() < 0.5:
        size = np.full(3, rng.uniform(0.05, 0.1))
        size[axis] = rng.uniform(0.8, 1.5)
        center = np.zeros(3)
        center[axis] = sign * (start + 0.5 * size[axis])
        center[2] = z
        parts.append(_part(_box(_v3(size), _v3(center)), rng, _APPENDAGE_DENSITY))
    else:
        mast = np.full(3, 0.06)
        mast[axis] = 0.35
        center = np.zeros(3)
        center[axis] = sign * (start + 0.175)
        center[2] = z
        parts.append(_part(_box(_v3(mast), _v3(center)), rng, _APPENDAGE_DENSITY))
        panel = np.array([0.03, 0.03, rng.uniform(0.6, 1.0)])
        panel[axis] = rng.uniform(1.0, 1.5)
        pc = np.zeros(3)
        pc[axis] = sign * (start + 0.35 - _EMBED_M + 0.5 * panel[axis])
        pc[2] = z
        parts.append(_part(_box(_v3(panel), _v3(pc)), rng, _APPENDAGE_DENSITY))
    rho, phi = 0.5 * r * np.sqrt(rng.random()), rng.uniform(0, 2 * np.pi)
    if rng.random() < 0.5:
        rho = 0.0
    port = (float(rho * np.cos(phi)), float(rho * np.sin(phi)), 0.5 * length)
    return parts, port, (0.0, 0.0, 1.0)


def _boxes_and_booms(rng: np.random.Generator) -> tuple[list[_Part], Vec3, Vec3]:
    half = 0.5 * rng.uniform(1.0, 2.0, 3)
    parts = [_part(_box(_v3(2 * half), (0, 0, 0)), rng, _BUS_DENSITY)]
    axis, sign = _MOUNT_FACES[int(rng.integers(4))]
    size = np.zeros(3)
    size[axis] = rng.uniform(2.0, 3.0)
    size[[k for k in range(3) if k != axis]] = rng.uniform(0.06, 0.12)
    parts.append(_part(_mounted_box(half, axis, sign, size, _off_centre(rng)), rng,
                       _APPENDAGE_DENSITY))
    # Smaller boxes on the other faces (never on the boom's face: the boom is the long feature).
    others = [f for f in _MOUNT_FACES if f != (axis, sign)]
    for _ in range(int(rng.integers(1, 4))):
        a, s = others[int(rng.integers(len(others)))]
        parts.append(_part(_appendage(rng, half, a, s, "box"), rng, _APPENDAGE_DENSITY))
    return parts, _port_on_top(rng, half, 0.5), (0.0, 0.0, 1.0)


_BUILDERS: dict[str, Callable[[np.random.Generator], tuple[list[_Part], Vec3, Vec3]]] = {
    "assembly": _assembly,
    "flat_face": _flat_face,
    "symmetric_plate": _symmetric_plate,
    "thin_frame": _thin_frame,
    "cylinder_bus": _cylinder_bus,
    "boxes_and_booms": _boxes_and_booms,
}

#: Kinds :func:`generate_target` builds.
SHAPE_KINDS: tuple[str, ...] = tuple(_BUILDERS)

_DESCRIPTIONS = {
    "assembly": "random assembly of a box bus and boxes, cylinders, plates and booms",
    "flat_face": "box bus with a plain flat docking face, an antenna and maybe a panel",
    "symmetric_plate": "square plate, port at the centre of +z (8 symmetric poses)",
    "thin_frame": "square frame of thin beams with a small docking plate",
    "cylinder_bus": "cylinder bus, port on its +z end face, a boom or panel",
    "boxes_and_booms": "box bus with smaller boxes and one long boom",
}


def _seed_of(rng: np.random.Generator | int) -> int:
    if isinstance(rng, np.random.Generator):
        return int(rng.integers(0, 2**31))
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool) and int(rng) >= 0:
        return int(rng)
    raise ValueError(f"rng={rng!r}; expected a numpy Generator or a seed int >= 0")


def generate_target(kind: str, rng: np.random.Generator | int = 0) -> TargetModel:
    """Build a random spacecraft of one of :data:`SHAPE_KINDS`.

    Args:
        kind: one of :data:`SHAPE_KINDS`.
        rng: a seed (>= 0), or a generator from which one seed is drawn; the target is then the one
            ``generate_target(kind, seed)`` builds, and its name says the seed.

    Returns:
        A :class:`TargetModel` named ``gen-<kind>-<seed>``, body frame at its centre of mass, port
        on the bus's flat +z face with its axis the outward normal, ``symmetries`` found from the
        mesh.

    Raises:
        ValueError: an unknown kind or a bad seed.
    """
    if kind not in _BUILDERS:
        raise ValueError(f"shape kind {kind!r}; expected one of {list(SHAPE_KINDS)}")
    seed = _seed_of(rng)
    parts, port, axis = _BUILDERS[kind](np.random.default_rng(seed))
    target = _assemble(f"gen-{kind}-{seed}", parts, port, axis, f"generated: {_DESCRIPTIONS[kind]}")
    target.symmetries = find_symmetries(target.mesh)
    return target


def save_generated(kind: str, seed: int, path: str | Path) -> tuple[FloatArray, FloatArray]:
    """Write a generated target's mesh as an STL file (body frame, metres).

    Args:
        kind: one of :data:`SHAPE_KINDS`.
        seed: seed (>= 0).
        path: output file; written as STL whatever its suffix.

    Returns:
        ``(port_position (3,) [m], port_axis (3,))`` in the file's frame, ready for
        ``load_target(path, port=...)``.
    """
    target = generate_target(kind, seed)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    target.mesh.export(out, file_type="stl")
    return target.port_position, target.port_axis
