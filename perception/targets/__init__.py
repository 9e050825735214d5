"""Target models: mesh + materials + docking port + mass properties, and the procedural library.

A ``TargetModel`` is everything the sensor simulator, the estimators and the dynamics need to know
about the object being approached, expressed in the **target body frame**, whose origin is the
target's centre of mass. The library targets are built procedurally from trimesh primitives so they
need no data files; any STL/OBJ/PLY/OFF/GLB/glTF mesh can be loaded with :func:`load_target` as well.

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

The package: :mod:`~perception.targets.model` (:class:`TargetModel`, materials, regions, port
frame), :mod:`~perception.targets.library` (the procedural library),
:mod:`~perception.targets.loading` (:func:`load_target` and mesh-file validation),
:mod:`~perception.targets.simplify` (dense meshes) and :mod:`~perception.targets.symmetry`
(:func:`find_symmetries`). Import from here.
"""

from __future__ import annotations

# The private names are the building blocks perception.shapes assembles its spacecraft from.
from perception.targets.library import (
    ENVELOPES_M,
    LIBRARY,
    _assemble,  # noqa: F401
    _box,  # noqa: F401
    _cylinder,  # noqa: F401
    _Part,  # noqa: F401
)
from perception.targets.loading import load_target
from perception.targets.model import Material, RegionOfInterest, TargetModel, has_embree, port_frame
from perception.targets.symmetry import find_symmetries

__all__ = [
    "ENVELOPES_M",
    "LIBRARY",
    "Material",
    "RegionOfInterest",
    "TargetModel",
    "find_symmetries",
    "has_embree",
    "load_target",
    "port_frame",
]
