"""Generated test spacecraft: port on the surface and facing out, sizes, determinism, symmetries."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from perception.shapes import SHAPE_KINDS, generate_target, save_generated
from perception.targets import TargetModel

SEEDS = (0, 1, 2, 7)


def test_kinds_cover_the_issue_list() -> None:
    assert {"assembly", "flat_face", "symmetric_plate", "thin_frame", "cylinder_bus",
            "boxes_and_booms"} <= set(SHAPE_KINDS)


@pytest.mark.parametrize("kind", SHAPE_KINDS)
@pytest.mark.parametrize("seed", SEEDS)
def test_generated_target_is_valid(kind: str, seed: int) -> None:
    t = generate_target(kind, seed)
    assert isinstance(t, TargetModel)
    assert t.name == f"gen-{kind}-{seed}"
    mesh = t.mesh
    assert np.all(np.isfinite(mesh.vertices))
    assert mesh.is_watertight and mesh.volume > 0
    assert 1.0 <= float(np.max(t.extents)) <= 6.0
    assert np.all((t.reflectivity >= 0.3) & (t.reflectivity <= 0.85))
    # Origin at the centre of mass: the parts' masses balance about it (first moment ~ 0 is what
    # _assemble guarantees; check the inertia is a valid tensor about it).
    ev = np.linalg.eigvalsh(t.inertia)
    assert np.all(ev > 0) and ev[0] + ev[1] >= ev[2] * (1 - 1e-9)
    # Port on the surface (1 mm) with its axis the outward normal of the face it stands on.
    _, dist, tri = trimesh.proximity.closest_point(mesh, t.port_position[None])
    assert dist[0] < 1e-3
    assert float(mesh.face_normals[tri[0]] @ t.port_axis) > 0.9
    np.testing.assert_allclose(np.linalg.norm(t.port_axis), 1.0, atol=1e-12)
    # Nothing in front of the port: a ray from 1 cm out along the axis leaves the target.
    assert not mesh.ray.intersects_any([t.port_position + 0.01 * t.port_axis], [t.port_axis])[0]
    # And from outside, looking back down the axis, the first hit is the port.
    origin = t.port_position + 10.0 * t.port_axis
    hits, _, _ = mesh.ray.intersects_location([origin], [-t.port_axis])
    first = hits[np.argmin(np.linalg.norm(hits - origin, axis=1))]
    np.testing.assert_allclose(first, t.port_position, atol=1e-6)


@pytest.mark.parametrize("kind", SHAPE_KINDS)
def test_same_seed_same_mesh(kind: str) -> None:
    a, b = generate_target(kind, 3), generate_target(kind, 3)
    assert a.mesh.vertices.tobytes() == b.mesh.vertices.tobytes()
    assert a.mesh.faces.tobytes() == b.mesh.faces.tobytes()
    assert a.reflectivity.tobytes() == b.reflectivity.tobytes()
    assert a.T_target_port.tobytes() == b.T_target_port.tobytes()
    assert a.model_hash == b.model_hash
    c = generate_target(kind, 4)
    assert c.model_hash != a.model_hash


def test_generator_draws_a_seed_that_names_the_target() -> None:
    t = generate_target("flat_face", np.random.default_rng(11))
    seed = int(t.name.rsplit("-", 1)[1])
    assert t.model_hash == generate_target("flat_face", seed).model_hash
    again = generate_target("flat_face", np.random.default_rng(11))
    assert again.model_hash == t.model_hash


def test_bad_kind_and_seed_rejected() -> None:
    with pytest.raises(ValueError, match="shape kind 'sphere'"):
        generate_target("sphere", 0)
    with pytest.raises(ValueError, match="rng=-1"):
        generate_target("assembly", -1)


@pytest.mark.parametrize("seed", SEEDS)
def test_symmetric_plate_has_the_dihedral_group(seed: int) -> None:
    t = generate_target("symmetric_plate", seed)
    # A square plate: 90/180/270 deg about its normal and 180 deg about four in-plane axes.
    assert len(t.symmetries) == 7
    angles = sorted(np.degrees(Rotation.from_matrix(np.array(t.symmetries)).magnitude()))
    np.testing.assert_allclose(angles, [90, 90, 180, 180, 180, 180, 180], atol=1e-6)
    for R in t.symmetries:
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
        _, d, _ = trimesh.proximity.closest_point(t.mesh, t.mesh.vertices @ R.T)
        assert d.max() < 1e-6
    # The four-fold axis is the port axis.
    quarter = [R for R in t.symmetries if abs(np.trace(R) - 1.0) < 1e-6]
    for R in quarter:
        np.testing.assert_allclose(R @ t.port_axis, t.port_axis, atol=1e-9)


@pytest.mark.parametrize("kind", ["assembly", "flat_face", "cylinder_bus", "boxes_and_booms"])
@pytest.mark.parametrize("seed", SEEDS)
def test_asymmetric_kinds_have_no_symmetry(kind: str, seed: int) -> None:
    t = generate_target(kind, seed)
    assert t.symmetries == []
    # And indeed: 180 deg about each principal axis moves some of the surface far off it.
    pts, _ = t.sample_surface(2000, seed=1)
    _, vecs = np.linalg.eigh(t.inertia)
    for k in range(3):
        R = Rotation.from_rotvec(np.pi * vecs[:, k]).as_matrix()
        _, d, _ = trimesh.proximity.closest_point(t.mesh, pts @ R.T)
        assert d.max() > 0.01 * np.max(t.extents)


def test_save_generated_writes_an_stl_with_the_port(tmp_path: Path) -> None:
    path = tmp_path / "flat.stl"
    pos, axis = save_generated("flat_face", 2, path)
    assert path.is_file() and path.read_bytes()[:5] != b"solid"  # binary STL
    mesh = trimesh.load(path, force="mesh")
    t = generate_target("flat_face", 2)
    np.testing.assert_allclose(mesh.bounds, t.mesh.bounds, atol=1e-6)
    _, d, _ = trimesh.proximity.closest_point(mesh, np.asarray(pos)[None])
    assert d[0] < 1e-3
    np.testing.assert_allclose(axis, t.port_axis)
