"""Ray casting against a target mesh with Embree (through trimesh), shared by the sensors.

Embree returns the first triangle each ray hits; the range is then recomputed in float64 from the
triangle's plane (Embree works in float32), which is exact for a flat facet and cheap. Rays are
given in the target frame; a rigid transform preserves distances, so the range along a unit
direction is the same in the sensor frame.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from perception.targets import TargetModel

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

__all__ = ["cast_from_sensor", "cast_rays", "face_planes", "sphere_hits"]


def face_planes(target: TargetModel) -> tuple[FloatArray, FloatArray]:
    """Per-face unit normals (F, 3) and plane offsets ``n . v0`` (F,) [m], cached on the target."""

    def build() -> tuple[FloatArray, FloatArray]:
        normals = np.ascontiguousarray(target.mesh.face_normals, dtype=np.float64)
        v0 = np.asarray(target.mesh.triangles[:, 0, :], dtype=np.float64)
        offsets = np.einsum("ij,ij->i", normals, v0)
        normals.setflags(write=False)
        offsets.setflags(write=False)
        return normals, offsets

    return target.cached(("sensor_face_planes",), build)  # type: ignore[no-any-return]


def cast_rays(
    target: TargetModel, origins_target: npt.ArrayLike, directions_target: FloatArray
) -> tuple[IntArray, FloatArray, FloatArray]:
    """First hit of every ray; one Embree call for all rays.

    Args:
        target: the target model.
        origins_target: (3,) one origin for all rays or (M, 3) per-ray origins [m], target frame.
        directions_target: (M, 3) unit directions, target frame.

    Returns:
        ``face`` (M,) int64 index of the face hit, -1 for a miss; ``rng`` (M,) range along the ray
        [m], NaN for a miss; ``cos_incidence`` (M,) cosine between the ray and the face's outward
        normal reversed (1 at normal incidence, <= 0 for a back face), NaN for a miss.
    """
    d = np.asarray(directions_target, dtype=np.float64).reshape(-1, 3)
    o = np.asarray(origins_target, dtype=np.float64)
    if d.shape[0] == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
    single = o.ndim == 1
    o_rays = np.broadcast_to(o, d.shape) if single else o.reshape(-1, 3)
    first = np.asarray(target.ray.intersects_first(o_rays, d), dtype=np.int64)
    normals, offsets = face_planes(target)
    # Dense over all rays (most rays of a steered scan hit): fewer calls than gathering the hits
    # and scattering them back; misses read face 0 and are masked at the end.
    hit = first >= 0
    f = np.where(hit, first, 0)
    n = normals[f]
    denom = np.einsum("ij,ij->i", n, d)
    if single:
        num = offsets[f] - n @ o
    else:
        num = offsets[f] - np.einsum("ij,ij->i", n, o_rays)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / denom
    ok = hit & (np.abs(denom) > 1e-12) & (t > 0)
    face = np.where(ok, first, -1)
    rng = np.where(ok, t, np.nan)
    cos_inc = np.where(ok, -denom, np.nan)
    return face, rng, cos_inc


def cast_from_sensor(
    target: TargetModel,
    T_sensor_target: FloatArray,
    directions_sensor: FloatArray,
    directions_sensor32: npt.NDArray[np.float32] | None = None,
) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
    """First hits of rays from the sensor origin with the target at one pose (compact output).

    Embree gets the rays rotated into the target frame in float32 (it works in float32 anyway);
    ranges and incidence are then computed in float64 from the hit faces' planes expressed in the
    sensor frame, so only the hits cost float64 work.

    Args:
        target: the target model.
        T_sensor_target: (4, 4) rigid pose.
        directions_sensor: (M, 3) unit ray directions, sensor frame.
        directions_sensor32: the same as float32 (pass a cached copy to skip the conversion).

    Returns:
        ``index`` (K,) rays that hit, ``face`` (K,) faces hit, ``rng`` (K,) ranges [m] and
        ``cos_incidence`` (K,) (<= 0 for back faces).
    """
    R = T_sensor_target[:3, :3]
    p = T_sensor_target[:3, 3]
    d32 = (
        directions_sensor.astype(np.float32) if directions_sensor32 is None else directions_sensor32
    )
    d_t = d32 @ R.astype(np.float32)
    o_t = np.broadcast_to((-(R.T @ p)).astype(np.float32), d_t.shape)
    first = np.asarray(target.ray.intersects_first(o_t, d_t), dtype=np.int64)
    idx = np.flatnonzero(first >= 0)
    return hit_ranges(target, T_sensor_target, idx, first[idx], directions_sensor[idx])


def hit_ranges(
    target: TargetModel, T_sensor_target: FloatArray, idx: IntArray, face: IntArray,
    directions_sensor: FloatArray,
) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
    """Ranges and incidence of rays ``idx`` (K,) that Embree found hitting faces ``face`` (K,),
    in float64 from the faces' planes in the sensor frame (the second half of
    :func:`cast_from_sensor`); ``directions_sensor`` (K, 3) are those rays' directions. Rays
    parallel to their face or hitting it behind the origin are dropped."""
    R = T_sensor_target[:3, :3]
    p = T_sensor_target[:3, 3]
    normals, offsets = face_planes(target)
    n_s = normals @ R.T  # (F, 3) face normals in the sensor frame
    off_s = offsets + n_s @ p
    f = face
    denom = np.einsum("ij,ij->i", n_s[f], directions_sensor)
    ok = np.abs(denom) > 1e-12
    t = np.divide(off_s[f], denom, out=np.full(idx.size, np.nan), where=ok)
    ok &= t > 0
    if not ok.all():
        idx, f, t, denom = idx[ok], f[ok], t[ok], denom[ok]
    return idx, f, t, -denom


def sphere_hits(directions: FloatArray, center: npt.ArrayLike, radius: float) -> FloatArray:
    """Range [m] at which rays from the origin enter a sphere (NaN for a miss).

    Args:
        directions: (M, 3) unit directions from the origin.
        center: (3,) sphere centre [m], same frame.
        radius: [m].

    Returns:
        (M,) first positive range to the sphere surface, NaN where a ray misses it.
    """
    c = np.asarray(center, dtype=np.float64).reshape(3)
    b = directions @ c
    cc = float(c @ c) - radius * radius
    disc = b * b - cc
    out = np.full(directions.shape[0], np.nan)
    hit = disc >= 0
    sq = np.sqrt(np.where(hit, disc, 0.0))
    if cc < 0:  # origin inside the sphere: every ray leaves through its far side
        return b + sq
    hit &= b > 0
    out[hit] = (b - sq)[hit]
    return out
