"""Target models: the library is valid and matches its documented envelopes; bad meshes fail clearly."""

from __future__ import annotations

import json
import pickle
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from perception.sensing.sensors.raycast import cast_rays
from perception.shapes import generate_target, save_generated
from perception.targets import ENVELOPES_M, LIBRARY, find_symmetries, has_embree, load_target
from perception.targets.mesh_size import triangle_bound


@pytest.mark.parametrize("name", sorted(LIBRARY))
def test_library_target_is_valid(name: str) -> None:
    t = load_target(name)
    mesh = t.mesh
    assert np.all(np.isfinite(mesh.vertices))
    assert mesh.is_watertight and mesh.is_winding_consistent
    # Outward normals: each closed part has positive volume, so the total signed volume is positive
    # and a ray from far outside hits a front face.
    assert mesh.volume > 0
    np.testing.assert_allclose(t.extents, ENVELOPES_M[name], atol=0.01)
    # Origin at the centre of mass: inertia is SPD and obeys the triangle inequality.
    ev = np.linalg.eigvalsh(t.inertia)
    assert np.all(ev > 0) and ev[0] + ev[1] >= ev[2] * (1 - 1e-9)
    assert t.reflectivity.shape == (len(mesh.faces),) and t.specular.shape == (len(mesh.faces),)
    assert np.all((t.reflectivity >= 0) & (t.reflectivity <= 1))
    # Port frame: rigid, axis unit, port on the hull (within 2 cm of the surface).
    T = t.T_target_port
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    _, dist, _ = trimesh.proximity.closest_point(mesh, t.port_position[None])
    assert dist[0] < 0.02
    # The approach axis points out of the target: a ray from outside along -axis hits the port.
    origin = t.port_position + 2.0 * t.port_axis
    hits, _, _ = mesh.ray.intersects_location([origin], [-t.port_axis])
    assert len(hits) and np.min(np.linalg.norm(hits - t.port_position, axis=1)) < 0.05
    assert {"whole", "docking_area", "port"} <= set(t.regions)
    assert t.symmetries == []


def test_library_has_asymmetric_features() -> None:
    # No mirror or 180-degree symmetry about the body axes: sample points do not map onto the mesh.
    for name in LIBRARY:
        t = load_target(name)
        pts, _ = t.sample_surface(2000, seed=1)
        for flip in (np.diag([-1, -1, 1]), np.diag([1, -1, -1]), np.diag([-1, 1, -1])):
            _, d, _ = trimesh.proximity.closest_point(t.mesh, pts @ flip.T)
            assert np.mean(d > 0.01) > 0.01, f"{name} looks symmetric under {np.diag(flip)}"
        assert find_symmetries(t.mesh) == []  # the finder agrees with the documented empty list


def test_cygnss_wings_dark_front_bright_back() -> None:
    t = load_target("cygnss")
    n = t.mesh.face_normals
    wing = np.abs(t.mesh.triangles_center[:, 0]) > 0.5
    front = wing & (n[:, 2] > 0.9)
    back = wing & (n[:, 2] < -0.9)
    assert front.any() and back.any()
    assert np.all(t.reflectivity[front] < 0.15) and np.all(t.reflectivity[back] > 0.5)


def test_surface_sampling_cached_and_area_uniform() -> None:
    t = load_target("cubesat")
    p1, n1 = t.sample_surface(5000, seed=3)
    p2, _ = t.sample_surface(5000, seed=3)
    assert p1 is p2  # cached per target
    assert not p1.flags.writeable
    np.testing.assert_allclose(np.linalg.norm(n1, axis=1), 1.0, atol=1e-12)
    _, d, _ = trimesh.proximity.closest_point(t.mesh, p1[:300])
    assert d.max() < 1e-9
    # Fraction of samples on the bus's +z face matches its share of the area.
    top = (np.abs(p1[:, 2] - (0.40 + t.mesh.bounds[0][2] + 0.46)) < 1e-6)
    del top  # the bus face z-coordinate depends on the CoM shift; use face areas instead
    areas = t.mesh.area_faces
    up = t.mesh.face_normals[:, 2] > 0.99
    frac_area = areas[up].sum() / areas.sum()
    frac_pts = np.mean(n1[:, 2] > 0.99)
    assert abs(frac_pts - frac_area) < 4 * np.sqrt(frac_area * (1 - frac_area) / 5000)


def test_embree_is_the_ray_backend() -> None:
    assert has_embree()
    t = load_target("cubesat")
    assert "embree" in type(t.ray).__module__


def test_pickle_rebuilds_caches() -> None:
    t = load_target("cygnss")
    t.sample_surface(100)
    t2 = pickle.loads(pickle.dumps(t))
    assert t2.cache == {}
    np.testing.assert_array_equal(t2.mesh.faces, t.mesh.faces)
    assert t2.model_hash == t.model_hash


def test_load_mesh_file_round_trip(tmp_path: Path) -> None:
    box = trimesh.creation.box(extents=(1000.0, 2000.0, 500.0))
    path = tmp_path / "box_mm.stl"
    box.export(path)
    with pytest.warns(UserWarning, match="no port given; put it at"):
        t = load_target(path, scale=0.001, mass=12.0)
    np.testing.assert_allclose(t.extents, [1.0, 2.0, 0.5], atol=1e-9)
    np.testing.assert_allclose(t.port_position, [0, 0, 0.25], atol=1e-9)
    # Uniform box inertia about its centre: m/12 (b^2 + c^2).
    np.testing.assert_allclose(np.diag(t.inertia), 12 / 12 * np.array([4.25, 1.25, 5.0]), rtol=1e-9)
    for ext in ("obj", "ply", "glb"):
        p = tmp_path / f"box.{ext}"
        box.export(p)
        with pytest.warns(UserWarning, match=f"box.{ext}: no port given"):
            assert load_target(p, scale=0.001).mesh.faces.shape[0] == 12


def test_bad_mesh_files_rejected(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nothing.stl"):
        load_target(tmp_path / "nothing.stl")
    with pytest.raises(ValueError, match="unknown target 'voyager'"):
        load_target("voyager")
    empty = tmp_path / "empty.stl"
    empty.write_bytes(b"")
    with pytest.raises(ValueError, match="empty.stl"):
        load_target(empty)
    flat = tmp_path / "flat.obj"
    flat.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n")
    with pytest.raises(ValueError, match="flat.obj has zero volume"):
        load_target(flat)
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\nf 1 4 2\nf 2 4 3\n")
    with pytest.raises(ValueError, match="nan.obj"):
        load_target(nan)
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"\x00\x01not a mesh")
    with pytest.raises(ValueError, match="garbage.ply"):
        load_target(garbage)


# ---------------------------------------------------------------------------------------------
# Mesh files from users: validation (issue 16)
# ---------------------------------------------------------------------------------------------
def _box_at(extents: tuple[float, ...], centre: tuple[float, ...]) -> trimesh.Trimesh:
    return trimesh.creation.box(
        extents=extents, transform=trimesh.transformations.translation_matrix(centre)
    )


def _one_line_refusal(path: Path, match: str, **kw: object) -> str:
    """Load ``path`` expecting a ValueError matching ``match``; the message is one line naming the
    file."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        with pytest.raises(ValueError, match=match) as info:
            load_target(path, **kw)  # type: ignore[arg-type]
    msg = str(info.value)
    assert "\n" not in msg and path.name in msg
    return msg


def test_library_targets_are_not_simplified() -> None:
    t = load_target("cubesat")
    assert t.model_mesh is t.mesh and t.simplification_deviation_m == 0.0


def test_non_finite_vertices_refused_before_processing(tmp_path: Path) -> None:
    # trimesh's processing would drop the bad vertex and its faces and load what is left.
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\nf 1 4 2\nf 2 4 3\n")
    msg = _one_line_refusal(nan, "nan.obj has non-finite vertex coordinates")
    assert "1 of 4 vertices" in msg
    inf = tmp_path / "inf.stl"
    facets = [((0, 0, 0), (1, 0, "inf"), (0, 1, 0)), ((0, 0, 0), (0, 1, 0), (0, 0, 1)),
              ((0, 0, 0), (0, 0, 1), (1, 0, 0)), ((1, 0, 0), (0, 0, 1), (0, 1, 0))]
    body = "".join(
        "facet normal 0 0 0\nouter loop\n"
        + "".join(f"vertex {x} {y} {z}\n" for x, y, z in f)
        + "endloop\nendfacet\n"
        for f in facets
    )
    inf.write_text(f"solid bad\n{body}endsolid bad\n")
    _one_line_refusal(inf, "inf.stl has non-finite vertex coordinates")


@pytest.fixture(scope="module")
def flat_face_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray, np.ndarray]:
    path = tmp_path_factory.mktemp("meshes") / "flat_face.stl"
    pos, axis = save_generated("flat_face", 3, path)
    return path, pos, axis


def test_explicit_port_on_the_surface_is_kept(flat_face_file) -> None:
    path, pos, axis = flat_face_file
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a correct port loads silently
        t = load_target(path, port=(pos, 2.0 * axis))
    _, d, _ = trimesh.proximity.closest_point(t.mesh, t.port_position[None])
    assert d[0] < 1e-3
    np.testing.assert_allclose(t.port_axis, axis, atol=1e-12)
    # Same geometry as the generated target: the port sits at the same place relative to the mesh.
    g = generate_target("flat_face", 3)
    np.testing.assert_allclose(t.port_position - t.bounds[0], g.port_position - g.bounds[0],
                               atol=1e-5)
    # A port a few centimetres off (inside the tolerance) is accepted as given.
    t2 = load_target(path, port=(pos + 0.03 * axis, axis))
    np.testing.assert_allclose(t2.port_position - t.port_position, 0.03 * axis, atol=1e-9)


def test_port_off_the_surface_refused_naming_the_distance(flat_face_file) -> None:
    path, pos, axis = flat_face_file
    msg = _one_line_refusal(path, r"is 0\.300 m from the surface", port=(pos + 0.3 * axis, axis))
    assert "port_tolerance_m=0.05" in msg
    # The tolerance is a keyword.
    t = load_target(path, port=(pos + 0.3 * axis, axis), port_tolerance_m=0.5)
    assert np.isfinite(t.port_position).all()


def test_port_axis_into_the_hull_refused_naming_the_angle(flat_face_file) -> None:
    path, pos, axis = flat_face_file
    _one_line_refusal(path, "points into the hull, 180 deg from the outward surface normal",
                      port=(pos, -axis))
    tilted = np.cos(np.radians(120)) * axis + np.sin(np.radians(120)) * np.cross(axis, [1, 0, 0])
    _one_line_refusal(path, "points into the hull, 120 deg", port=(pos, tilted))
    for bad in ([0.0, 0.0, 0.0], [np.nan, 0.0, 1.0]):
        _one_line_refusal(path, "port axis .* must be finite and non-zero", port=(pos, bad))
    _one_line_refusal(path, "port position .* must be finite", port=([np.inf, 0, 0], axis))


@pytest.mark.parametrize("inverted", [False, True])
def test_port_on_an_open_mesh_judged_by_rays(tmp_path: Path, inverted: bool) -> None:
    # A box without its bottom: winding cannot say which side is out, escaping rays (or, through
    # the hole, the side away from the centre) do, whichever way the file's faces are wound.
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    box.update_faces(box.face_normals[:, 2] > -0.5)
    box.remove_unreferenced_vertices()
    if inverted:
        box.invert()
    path = tmp_path / "open.stl"
    box.export(path)
    t = load_target(path, port=((0.2, 0.1, 0.5), (0.0, 0.0, 1.0)))
    assert not t.mesh.is_watertight
    _one_line_refusal(path, "points into the hull, 180 deg", port=((0.2, 0.1, 0.5), (0, 0, -1.0)))
    _one_line_refusal(path, "points into the hull, 180 deg", port=((0.5, 0.1, 0.2), (-1.0, 0, 0)))


def test_port_whose_approach_crosses_the_target_refused(tmp_path: Path) -> None:
    # A port on the bus's +x face looking along +x, with a plate standing 0.5 m in front of it.
    parts = [_box_at((1, 1, 1), (0, 0, 0)), _box_at((0.05, 0.6, 0.6), (1.0, 0, 0)),
             _box_at((0.5, 0.05, 0.05), (0.75, 0.25, 0.25))]
    path = tmp_path / "blocked.stl"
    trimesh.util.concatenate(parts).export(path)
    _one_line_refusal(path, r"a ray from the port along its axis .* meets the target again 0\.47",
                      port=((0.5, 0.0, 0.0), (1.0, 0.0, 0.0)))


def test_missing_port_warns_where_and_how_far(tmp_path: Path) -> None:
    # A mast on top lifts the bounding box 0.5 m above the bus face the port should go on.
    bus = _box_at((1.0, 1.0, 1.0), (0, 0, 0))
    mast = _box_at((0.05, 0.05, 0.5), (0.3, 0.3, 0.75))
    path = tmp_path / "masted.stl"
    trimesh.util.concatenate([bus, mast]).export(path)
    with pytest.warns(UserWarning, match=r"masted\.stl: no port given; put it at \(0, 0, 0\.5\) m"
                      r" .*0\.500 m from that face centre") as rec:
        t = load_target(path)
    assert all("\n" not in str(w.message) for w in rec)
    _, d, _ = trimesh.proximity.closest_point(t.mesh, t.port_position[None])
    assert d[0] < 1e-6
    np.testing.assert_allclose(t.port_axis, [0, 0, 1], atol=1e-12)


def test_missing_port_on_a_frame_lands_on_a_beam(tmp_path: Path) -> None:
    path = tmp_path / "frame.stl"
    save_generated("thin_frame", 1, path)
    with pytest.warns(UserWarning, match="a ray through the centre misses the mesh"):
        t = load_target(path)
    _, d, tri = trimesh.proximity.closest_point(t.mesh, t.port_position[None])
    assert d[0] < 1e-6 and t.mesh.face_normals[tri[0]] @ t.port_axis > 0.99


def test_millimetre_mesh_refused_unless_scaled(tmp_path: Path) -> None:
    path = tmp_path / "bus_mm.stl"
    trimesh.creation.box(extents=(1200.0, 800.0, 500.0)).export(path)
    for scale in (None, 1.0):  # 1.0 is what a config's default passes: not a deliberate scale
        msg = _one_line_refusal(path, "is 1200 m across at scale=1", scale=scale)
        assert "scale=0.001" in msg
    with pytest.warns(UserWarning, match="no port given"):
        t = load_target(path, scale=0.001)
    np.testing.assert_allclose(t.extents, [1.2, 0.8, 0.5], atol=1e-9)
    with pytest.warns(UserWarning, match="no port given"):
        assert load_target(path, max_extent_m=2000.0).extents[0] == pytest.approx(1200.0)


def test_an_oversized_mesh_file_is_refused_before_it_is_read(tmp_path: Path) -> None:
    path = tmp_path / "big.stl"
    trimesh.creation.icosphere(subdivisions=4).export(path)
    with pytest.raises(ValueError, match=r"big.stl is 0 MiB, more than max_file_bytes=0 MiB"):
        load_target(path, max_file_bytes=1000)


def _triangle_files(tmp_path: Path) -> list[tuple[Path, int]]:
    """Each test solid in every format read, with the triangles trimesh makes of it."""
    solids = {
        "box": trimesh.creation.box(extents=(1.0, 2.0, 3.0)),
        "sphere": trimesh.creation.icosphere(subdivisions=4),
        "cylinder": trimesh.creation.cylinder(radius=0.5, height=2.0, sections=37),
    }
    out = []
    for name, mesh in solids.items():
        for ext, kw in [("obj", {}), ("ply", {}), ("ply", {"encoding": "ascii"}), ("off", {}),
                        ("glb", {}), ("gltf", {})]:
            path = tmp_path / f"{name}_{len(out)}.{ext}"
            mesh.export(path, **kw)
            out.append((path, len(trimesh.load(path, force="mesh", process=False).faces)))
    return out


def test_triangle_bound_is_exact_on_triangles_and_bounds_polygons(tmp_path: Path) -> None:
    for path, faces in _triangle_files(tmp_path):
        assert triangle_bound(path) == faces, path.name
    polygon = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0.5 1.5 0\n"
    obj = tmp_path / "poly.obj"  # a pentagon fans into 3 triangles; a line with texture indices
    obj.write_text(polygon + "f 1 2 3 5 4\nf 1/1 2/2 3/3\nfoo 1 2 3 4 5 6\n")
    assert triangle_bound(obj) == 4 == len(trimesh.load(obj, force="mesh", process=False).faces)
    ply = tmp_path / "poly.ply"
    ply.write_text("ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y"
                   "\nproperty float z\nelement face 2\nproperty list uchar int vertex_indices\n"
                   "end_header\n" + polygon.replace("v ", "") + "5 0 1 2 4 3\n3 0 1 2\n")
    assert triangle_bound(ply) == 4 == len(trimesh.load(ply, force="mesh", process=False).faces)
    off = tmp_path / "poly.off"
    off.write_text("# exported\nOFF\n5 2 0\n" + polygon.replace("v ", "") + "5 0 1 2 4 3\n3 0 1 2\n")
    assert triangle_bound(off) == 4
    stl = tmp_path / "s.stl"  # at least 50 bytes a triangle: the file size bounds it
    trimesh.creation.box().export(stl)
    assert triangle_bound(stl) is None


def test_a_file_making_too_many_triangles_is_refused_before_it_is_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def never(*args: object, **kw: object) -> None:
        raise AssertionError("trimesh.load was called on a refused file")

    dense = tmp_path / "dense.obj"  # 8 bytes a triangle: 2.4 MB make 300,000 of them
    dense.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n" + "f 1 2 3\n" * 300_000)
    fan = tmp_path / "fan.obj"  # one face line, 300,000 triangles
    fan.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf " + " ".join(["1 2 3"] * 100_000) + " 1 2\n")
    box = tmp_path / "box.gltf"
    trimesh.creation.box().export(box)
    doc = json.loads(box.read_text())
    many = tmp_path / "instanced.gltf"  # 12 triangles reached 1000 x 1000 times through the tree
    doc["nodes"] = [{"mesh": 0}, {"children": [0] * 1000}, {"children": [1] * 1000}]
    doc["scenes"] = [{"nodes": [2]}]
    many.write_text(json.dumps(doc))
    looped = tmp_path / "looped.gltf"
    doc["nodes"] = [{"mesh": 0, "children": [1]}, {"children": [0]}]
    doc["scenes"] = [{"nodes": [0]}]
    looped.write_text(json.dumps(doc))
    archive = tmp_path / "bomb.zip"
    archive.write_bytes(b"PK\x05\x06" + b"\x00" * 18)
    monkeypatch.setattr(trimesh, "load", never)
    assert "300,000 triangles, more than max_file_faces=100,000" in _one_line_refusal(
        dense, "makes up to", max_file_faces=100_000)
    _one_line_refusal(fan, "makes up to 300,000 triangles", max_file_faces=100_000)
    _one_line_refusal(many, "makes up to 12,000,000 triangles, more than max_file_faces=6,000,000")
    _one_line_refusal(looped, "node hierarchy has a cycle through node 0")
    _one_line_refusal(archive, "format '.zip' is not read; expected one of .stl, .obj")


def test_dense_mesh_gets_a_simplified_model_mesh(tmp_path: Path) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=7, radius=1.5)  # 327,680 faces
    path = tmp_path / "dense.stl"
    sphere.export(path)
    # (Load time is a benchmark's business, not a test's: ~4 s here on a quiet machine.)
    with pytest.warns(UserWarning, match=r"327680 faces > max_model_faces=20000; ICP and PAH use"):
        t = load_target(path, port=((0.0, 0.0, 1.5), (0.0, 0.0, 1.0)))
    assert len(t.mesh.faces) == 327_680  # the sensor keeps the full mesh
    assert t.model_mesh is not t.mesh and 1_000 < len(t.model_mesh.faces) <= 20_000
    # The model side sees the simplified mesh as a target of its own: its ray casts index the
    # faces its face grid and face planes index.
    view = t.model_view()
    assert view is t.model_view() and view.mesh is t.model_mesh
    assert view.reflectivity.shape == (len(t.model_mesh.faces),)
    d = np.tile([0.0, 0.0, -1.0], (50, 1))
    o = np.column_stack([np.linspace(-1, 1, 50), np.zeros(50), np.full(50, 3.0)])
    face, rng_m, _ = cast_rays(view, o, d)
    assert face.max() < len(t.model_mesh.faces) and np.all(face >= 0)
    expected = np.sqrt(1.5**2 - o[:, 0] ** 2)
    np.testing.assert_allclose(3.0 - rng_m, expected, atol=t.simplification_deviation_m + 1e-3)
    assert 0.0 < t.simplification_deviation_m < 0.005
    # The reported deviation bounds what an outside reference measures on the simplified vertices.
    v = t.model_mesh.vertices[:: max(1, len(t.model_mesh.vertices) // 300)]
    _, d, _ = trimesh.proximity.closest_point(t.mesh, v)
    assert d.max() <= 1.5 * t.simplification_deviation_m + 1e-4
    # It survives a trip to a worker process.
    t2 = pickle.loads(pickle.dumps(t))
    np.testing.assert_array_equal(t2.model_mesh.faces, t.model_mesh.faces)
    assert t2.simplification_deviation_m == t.simplification_deviation_m


def test_loaded_plate_symmetries_found_and_true(tmp_path: Path) -> None:
    path = tmp_path / "plate.stl"
    pos, axis = save_generated("symmetric_plate", 2, path)
    t = load_target(path, port=(pos, axis))
    assert len(t.symmetries) == 7  # square plate: the dihedral group of order 8
    for R in t.symmetries:
        _, d, _ = trimesh.proximity.closest_point(t.mesh, t.mesh.vertices @ R.T)
        assert d.max() < 1e-5


def test_loaded_assembly_has_no_symmetry(tmp_path: Path) -> None:
    path = tmp_path / "assembly.stl"
    pos, axis = save_generated("assembly", 4, path)
    assert load_target(path, port=(pos, axis)).symmetries == []


def test_find_symmetries_on_reference_solids() -> None:
    # Rotation groups: rectangular box D2 (3), cube O (23), hexagonal prism D6 (11).
    assert len(find_symmetries(trimesh.creation.box(extents=(2.0, 1.5, 0.3)))) == 3
    assert len(find_symmetries(trimesh.creation.box(extents=(1.0, 1.0, 1.0)))) == 23
    assert len(find_symmetries(trimesh.creation.cylinder(0.5, 2.0, sections=6))) == 11
    wedge = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    wedge = trimesh.util.concatenate([wedge, _box_at((0.3, 0.3, 0.3), (0.8, 0.3, 0.4))])
    wedge.apply_translation(-wedge.center_mass)
    assert find_symmetries(wedge) == []
