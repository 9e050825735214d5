"""Flash frames cast only the rays that can hit (FlashLidar.rays_to_cast) and stay bitwise the
frames of the full cast: on library targets and on shapes made here, at every kind of pose."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from perception.config import FlashLidarConfig
from perception.geometry import make_T
from perception.sensing.pointcloud import PointCloud
from perception.sensing.sensors import FlashLidar
from perception.targets import TargetModel, load_target

ROOT = Path(__file__).resolve().parents[2]
FIELDS = (
    "points",
    "times",
    "subsystem",
    "intensity",
    "sigma",
    "directions",
    "true_points",
    "spurious",
    "organized",
    "valid_mask",
)


def own_shape(kind: str, seed: int = 0) -> TargetModel:
    """A shape generated here: ``blob`` (a random convex hull off its origin, so the box is not
    centred on the body frame), ``lshape`` (two boxes, a concave outline) or ``speck`` (a 2 cm
    cube: a handful of pixels far out)."""
    rng = np.random.default_rng(seed)
    if kind == "blob":
        mesh = trimesh.convex.convex_hull(
            rng.normal(size=(40, 3)) * [1.5, 0.6, 0.3] + [0.8, -0.3, 0.2]
        )
    elif kind == "lshape":
        mesh = trimesh.util.concatenate(
            [
                trimesh.creation.box(
                    extents=(2.0, 0.4, 0.4), transform=make_T(None, [0.6, 0.0, 0.0])
                ),
                trimesh.creation.box(
                    extents=(0.4, 1.6, 0.4), transform=make_T(None, [-0.2, 0.6, 0.0])
                ),
            ]
        )
    else:
        mesh = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    nf = len(mesh.faces)
    return TargetModel(
        kind, mesh, rng.uniform(0.2, 0.9, nf), np.zeros(nf, bool), np.eye(4), 10.0, np.eye(3)
    )


def poses(rng: np.random.Generator, n: int) -> Iterator[np.ndarray]:
    """Random attitudes at ranges from inside the target to beyond max range, on the boresight,
    across the edge of the field of view, beside and behind the sensor."""
    for k in range(n):
        R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
        r = float(rng.choice([0.05, 0.4, 1.0, 3.0, 8.0, 20.0, 40.0, 60.0, 149.0, 152.0, 400.0]))
        kind = k % 4
        if kind == 0:  # near the boresight
            d = np.array([*rng.normal(0.0, 0.05, 2), 1.0])
        elif kind == 1:  # straddling the edge of the 20 deg field of view
            a = np.radians(rng.uniform(8.0, 12.0))
            d = np.array([np.sin(a), rng.normal(0.0, 0.1), np.cos(a)])
        elif kind == 2:  # anywhere, behind the sensor included
            d = rng.normal(size=3)
        else:  # beside the image plane
            d = np.array([*rng.normal(size=2), rng.normal(0.0, 0.05)])
        yield make_T(R, r * d / np.linalg.norm(d))


def assert_same_frame(a: PointCloud, b: PointCloud) -> None:
    for name in FIELDS:
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert x.tobytes() == y.tobytes(), name
    assert (a.t_start, a.t_end) == (b.t_start, b.t_end)


def culled_and_full(
    lidar: FlashLidar, target: TargetModel, T: np.ndarray, seed: int
) -> tuple[PointCloud, PointCloud]:
    rng_a, rng_b = np.random.default_rng(seed), np.random.default_rng(seed)
    a = lidar.capture(target, T, rng_a, t=1.5)
    b = lidar.capture(target, T, rng_b, t=1.5, cull=False)
    # the same draws: the generators end in the same state
    assert rng_a.bit_generator.state == rng_b.bit_generator.state
    return a, b


@contextmanager
def embree_calls(target: TargetModel) -> Iterator[list[tuple[np.ndarray, np.ndarray]]]:
    """Records (origins, directions) of every Embree cast on ``target``."""
    calls: list[tuple[np.ndarray, np.ndarray]] = []
    ray = target.ray
    original = ray.intersects_first

    def spy(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        calls.append((np.array(origins), np.array(directions)))
        return original(origins, directions)

    ray.intersects_first = spy
    try:
        yield calls
    finally:
        del ray.intersects_first


@pytest.fixture(scope="module")
def lidar() -> FlashLidar:
    return FlashLidar()


@pytest.mark.parametrize("name", ["cygnss", "cubesat", "blob", "lshape", "speck"])
def test_culled_frame_is_bitwise_the_full_frame(lidar: FlashLidar, name: str) -> None:
    target = load_target(name) if name in ("cygnss", "cubesat") else own_shape(name)
    rng = np.random.default_rng(sum(map(ord, name)))
    n_points = 0
    for k, T in enumerate(poses(rng, 20)):
        a, b = culled_and_full(lidar, target, T, seed=k)
        assert_same_frame(a, b)
        n_points += len(a)
    assert n_points > 1000  # the poses do see the target


def test_culled_frame_near_and_far_on_other_sensors() -> None:
    """Other grids and fields of view, and min_range_m = 0 (a box across the image plane can then
    not be bounded: every ray is cast)."""
    target = own_shape("blob", 3)
    rng = np.random.default_rng(11)
    for cfg in (
        FlashLidarConfig(rows=64, cols=96, fov_deg=(40.0, 25.0), min_range_m=0.0),
        FlashLidarConfig(
            rows=120, cols=80, fov_deg=(8.0, 12.0), max_range_m=30.0, error_model="gaussian"
        ),
    ):
        lidar = FlashLidar(cfg)
        for k, T in enumerate(poses(rng, 30)):
            assert_same_frame(*culled_and_full(lidar, target, T, seed=k))
    inside = make_T(None, [0.1, 0.0, 0.2])  # the sensor inside the body's box
    assert FlashLidar(FlashLidarConfig(min_range_m=0.0)).rays_to_cast(target, inside) is None


def test_every_cast_ray_gets_the_full_casts_float32_direction(lidar: FlashLidar) -> None:
    """Embree sees the very rays of the full cast (a ray rotated alone rounds differently under
    some BLAS kernels): checked here, and in a process forced onto OpenBLAS's Haswell kernels."""
    check_embree_inputs(lidar)
    code = textwrap.dedent("""
        from perception.sensing.sensors import FlashLidar
        from tests.perception.test_flash_cull import check_embree_inputs
        check_embree_inputs(FlashLidar())
    """)
    env = {**os.environ, "OPENBLAS_CORETYPE": "Haswell"}
    done = subprocess.run(
        [sys.executable, "-c", code],
        check=False,
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]


def check_embree_inputs(lidar: FlashLidar) -> None:
    """Culled and full casts of a few poses: the culled rays' Embree inputs are the full cast's
    rows, bitwise (a 2 cm cube at 140 m: one to four rays; the CYGNSS at 30 m)."""
    rng = np.random.default_rng(5)
    for target, r in ((own_shape("speck"), 140.0), (load_target("cygnss"), 30.0)):
        for _ in range(6):
            # centred on a random pixel's ray: the speck (a third of a pixel) is cast
            pixel = lidar.pixel_directions[rng.integers(len(lidar.pixel_directions))]
            T = make_T(
                Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix(), r * pixel
            )
            rays = lidar.rays_to_cast(target, T)
            assert rays is not None and 0 < rays.size < 60_000
            with embree_calls(target) as calls:
                a, b = culled_and_full(lidar, target, T, seed=0)
            (o_c, d_c), (o_f, d_f) = calls
            assert d_c.tobytes() == d_f[rays].tobytes()
            assert o_c.tobytes() == o_f[rays].tobytes()
            assert_same_frame(a, b)


@pytest.mark.parametrize("range_m, most", [(20.0, 0.15), (40.0, 0.04), (60.0, 0.02)])
def test_far_fewer_rays_are_cast(lidar: FlashLidar, range_m: float, most: float) -> None:
    """At 20-60 m the CYGNSS covers a few percent of the image: count the rays Embree gets."""
    target = load_target("cygnss")
    rng = np.random.default_rng(int(range_m))
    cast = []
    for _ in range(12):
        T = make_T(
            Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix(),
            [*rng.uniform(-1.0, 1.0, 2), range_m],
        )
        with embree_calls(target) as calls:
            frame = lidar.capture(target, T, np.random.default_rng(0))
        assert len(calls) == 1 and len(frame) > 0
        cast.append(len(calls[0][1]))
    full = lidar.shape[0] * lidar.shape[1]
    assert max(cast) <= most * full
    assert np.median(cast) <= 0.6 * most * full


def test_nothing_is_cast_when_nothing_can_return(lidar: FlashLidar) -> None:
    target = load_target("cygnss")
    for T in (
        make_T(None, [0.0, 0.0, -15.0]),  # behind
        make_T(None, [40.0, 0.0, 10.0]),  # outside the field of view
        make_T(None, [0.0, 0.0, 160.0]),  # beyond max_range_m (150 m) by more than its size
        make_T(None, [0.0, 0.0, 0.1]),
    ):  # inside its box: every return under min_range_m
        rays = lidar.rays_to_cast(target, T)
        assert rays is not None and rays.size == 0
        with embree_calls(target) as calls:
            frame = lidar.capture(target, T, np.random.default_rng(0))
        assert calls == [] and len(frame) == 0
        assert_same_frame(frame, lidar.capture(target, T, np.random.default_rng(0), cull=False))
