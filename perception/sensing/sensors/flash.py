"""Flash LiDAR (seed 003 section 3.1): a grid of pixels captured at one instant.

Each pixel's ray is intersected with the target mesh (step 2 of seed 003), and a range error
``delta_d`` is added along the ray (eq. 18): uniform in ``[-range_error_m, range_error_m]``
(the seed's maximum absolute error, covering bias and noise) or Gaussian with sigma
``range_error_m``. All pixels share one time, so a moving target is not distorted.

Pixel geometry uses the angle convention of :mod:`perception.sensing.scan_patterns`: pixel ``(r, c)``
looks at ``az = ((c + 0.5) / cols - 0.5) * fov_h`` (toward +x) and, downward (+y),
``((r + 0.5) / rows - 0.5) * fov_v`` — equal angular steps per pixel, as in seed 003 eq. (4).
Row 0 is the top of the image. Pixels beyond ``grazing_limit_deg`` of incidence or outside
``[min_range_m, max_range_m]`` are invalid (NaN in the organised grid). Materials only set the
intensity (reflectivity * cos(incidence)); the seed's simulator has no link budget.

Culling: a 250,000-pixel frame of a target 20-60 m away has a few thousand rays that can hit;
the others would cost most of the cast for nothing. :meth:`FlashLidar.rays_to_cast` keeps the
pixels inside the image outline of the target's bounding box (padded by :data:`CULL_PAD_M`,
clipped at the depth nearer than which any return is under ``min_range_m``), from the pose the
frame is captured at. That outline is the convex hull of the box's projected corners in the
plane ``z = 1``, where a pixel's ray sits at ``x/z = tan(az)`` (its column) and
``y/z = tan(down)`` (its row): per row, the hull's chord is a run of columns. Only those rays go
to Embree, and the frame is bitwise the frame of the full cast: a ray left out would have missed
(or returned from outside the range window), each cast ray gets the very float32 direction the
full cast gives it, and the range errors are drawn for the same valid pixels in the same order.
The directions: the same float32 matrix product on fewer rows gives each row the same bits
(OpenBLAS's sgemm; checked on the 16 x86-64 core types ``OPENBLAS_CORETYPE`` selects, Core2 to
SapphireRapids, and in the tests), except a single row, which numpy hands to sgemv and the
Haswell and Zen kernels round differently: a lone ray is rotated as a pair. (Rotating the whole
grid and gathering would not lean on that, but costs a 250,000-row product whose two OpenBLAS
threads stall for tens of milliseconds on a busy machine.)
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from perception.config import FlashLidarConfig
from perception.geometry import check_rigid
from perception.sensing.pointcloud import PointCloud, Subsystem
from perception.sensing.scan_patterns import angles_to_directions
from perception.sensing.sensors.raycast import cast_from_sensor, hit_ranges
from perception.targets import TargetModel

FloatArray = npt.NDArray[np.float64]
IndexArray = npt.NDArray[np.intp]

__all__ = ["CULL_PAD_M", "FlashLidar"]

#: Padding [m] of the target's bounding box when culling rays: far above what float32 costs
#: Embree (a hit ~1e-5 m off the float64 geometry at 150 m), so no ray that Embree could report
#: as a hit is left out.
CULL_PAD_M = 0.005

#: Padding of the culling outline in the image plane [tangent units]: the rounding of the
#: projection and of a pixel's ``x/z`` (a pixel is ~7e-4 wide here).
_CULL_PAD_TAN = 1e-6

#: The 12 edges of a box whose corners are numbered by the bits (x, y, z) of their index.
_BOX_EDGES = np.array([(i, i | b) for i in range(8) for b in (1, 2, 4) if not i & b])


class FlashLidar:
    """Grid sensor of seed 003.

    Args:
        config: resolution, field of view and error model.

    Example:
        >>> import numpy as np
        >>> from perception.geometry import make_T
        >>> from perception.targets import load_target
        >>> frame = FlashLidar().capture(load_target("cygnss"), make_T(None, [0, 0, 15.0]),
        ...                              np.random.default_rng(0))
        >>> frame.organized.shape
        (500, 500, 3)
    """

    def __init__(self, config: FlashLidarConfig | None = None) -> None:
        self.config = config or FlashLidarConfig()
        c = self.config
        fov_h, fov_v = (math.radians(v) for v in c.fov_deg)
        az = ((np.arange(c.cols) + 0.5) / c.cols - 0.5) * fov_h
        down = ((np.arange(c.rows) + 0.5) / c.rows - 0.5) * fov_v
        AZ, DOWN = np.meshgrid(az, down)  # (rows, cols)
        self._dirs = np.ascontiguousarray(angles_to_directions(AZ, -DOWN).reshape(-1, 3))
        self._dirs.setflags(write=False)
        self._dirs32 = self._dirs.astype(np.float32)
        self._cos_grazing = math.cos(math.radians(c.grazing_limit_deg))
        # x/z of column c's rays and y/z of row r's rays (both increasing), and the smallest z of
        # any ray: a return nearer than min_range_m * that has z below it.
        self._tan_az = np.tan(az)
        self._tan_down = np.tan(down)
        self._z_near = c.min_range_m * float(self._dirs[:, 2].min()) * (1.0 - 1e-9)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the pixel grid."""
        return self.config.rows, self.config.cols

    @property
    def pixel_directions(self) -> FloatArray:
        """(rows * cols, 3) unit ray direction of every pixel, row-major, sensor frame."""
        return self._dirs

    @property
    def range_sigma(self) -> float:
        """1-sigma range error [m] of the configured error model."""
        d = self.config.range_error_m
        return d / math.sqrt(3.0) if self.config.error_model == "uniform" else d

    def rays_to_cast(
        self, target: TargetModel, T_sensor_target: npt.ArrayLike
    ) -> IndexArray | None:
        """The pixels whose rays can return from ``target`` at this pose (see the module docstring).

        Args:
            target: the target model.
            T_sensor_target: (4, 4) target pose in the sensor frame.

        Returns:
            (K,) row-major pixel indices, increasing (per row a run of columns; empty when the
            target is behind the sensor, outside the field of view or beyond ``max_range_m``), or
            None for every pixel (all of them can return, or the box crosses the sensor's image
            plane and ``min_range_m`` is 0).
        """
        return self._rays_to_cast(target, check_rigid(T_sensor_target, "T_sensor_target"))

    def _rays_to_cast(self, target: TargetModel, T: FloatArray) -> IndexArray | None:
        c = self.config
        lo, hi = _padded_bounds(target)
        R, p = T[:3, :3], T[:3, 3]
        empty = np.zeros(0, dtype=np.intp)
        o_target = -(R.T @ p)  # the sensor origin in the target frame
        gap = np.maximum(np.maximum(lo - o_target, o_target - hi), 0.0)
        if float(np.linalg.norm(gap)) > c.max_range_m:
            return empty
        corners = np.where(np.arange(8)[:, None] >> np.arange(3) & 1, hi, lo) @ R.T + p
        z = corners[:, 2]
        front = z >= self._z_near
        if not front.any():
            return empty
        if not front.all():
            if self._z_near <= 0.0:
                return None
            # The box clipped at z_near: its front corners and the crossings of its edges.
            i, j = _BOX_EDGES[front[_BOX_EDGES[:, 0]] != front[_BOX_EDGES[:, 1]]].T
            s = (self._z_near - z[i]) / (z[j] - z[i])
            crossings = corners[i] + s[:, None] * (corners[j] - corners[i])
            crossings[:, 2] = self._z_near
            corners = np.vstack([corners[front], crossings])
        u = corners[:, 0] / corners[:, 2]
        v = corners[:, 1] / corners[:, 2]
        c0, c1 = np.searchsorted(self._tan_az, [u.min() - _CULL_PAD_TAN, u.max() + _CULL_PAD_TAN])
        r0, r1 = np.searchsorted(self._tan_down, [v.min() - _CULL_PAD_TAN, v.max() + _CULL_PAD_TAN])
        if c0 >= c1 or r0 >= r1:
            return empty
        # Each row's columns: the chord of the outline (the convex hull of the projected corners)
        # at the row's height, clamped into the outline's height for the rows of the padding.
        rows = np.arange(r0, r1)
        lo_u, hi_u = _hull_chords(_convex_hull(u, v), self._tan_down[rows])
        cl = np.searchsorted(self._tan_az, lo_u - _CULL_PAD_TAN)
        ch = np.maximum(np.searchsorted(self._tan_az, hi_u + _CULL_PAD_TAN, side="right"), cl)
        n = ch - cl
        total = int(n.sum())
        if total == c.rows * c.cols:
            return None
        # row-major indices of every row's run of columns, increasing
        starts = rows * c.cols + cl - (np.cumsum(n) - n)
        return np.repeat(starts, n) + np.arange(total)

    def _cast(
        self, target: TargetModel, T: FloatArray, rays: IndexArray | None
    ) -> tuple[IndexArray, IndexArray, FloatArray, FloatArray]:
        """:func:`~perception.sensing.sensors.raycast.cast_from_sensor` of the pixels ``rays``
        (None: all), each ray's result bitwise that of the full cast."""
        if rays is None:
            return cast_from_sensor(target, T, self._dirs, self._dirs32)
        if rays.size == 0:
            return rays, rays, np.zeros(0), np.zeros(0)
        R, p = T[:3, :3], T[:3, 3]
        # The full cast's float32 rows (module docstring): one row goes through sgemm as a pair.
        pick = rays if rays.size > 1 else np.repeat(rays, 2)
        d_t = (self._dirs32[pick] @ R.astype(np.float32))[: rays.size]
        o_t = np.broadcast_to((-(R.T @ p)).astype(np.float32), d_t.shape)
        first = np.asarray(target.ray.intersects_first(o_t, d_t), dtype=np.int64)
        local = np.flatnonzero(first >= 0)
        idx = rays[local]
        # From here cast_from_sensor's float64 steps on the same arrays as the full cast's.
        return hit_ranges(target, T, idx, first[local], self._dirs[idx])

    def capture(
        self,
        target: TargetModel,
        T_sensor_target: npt.ArrayLike,
        rng: np.random.Generator,
        t: float = 0.0,
        *,
        cull: bool = True,
    ) -> PointCloud:
        """One frame.

        Args:
            target: the target model.
            T_sensor_target: (4, 4) target pose in the sensor frame at time ``t``.
            rng: the only source of randomness.
            t: capture time [s].
            cull: cast only :meth:`rays_to_cast` (the frame is the same bitwise; False casts
                every pixel, for comparison).

        Returns:
            An organised cloud: ``organized`` (rows, cols, 3) with NaN at invalid pixels,
            ``valid_mask`` (rows, cols) and the valid points in row-major pixel order.
        """
        T = check_rigid(T_sensor_target, "T_sensor_target")
        if not math.isfinite(t):
            raise ValueError(f"t={t!r}; expected a finite time [s]")
        if not isinstance(rng, np.random.Generator):
            # a ValueError, as for every other bad argument here
            raise ValueError(f"rng={rng!r}; expected a numpy.random.Generator")  # noqa: TRY004
        c = self.config
        rows, cols = c.rows, c.cols
        hit, face, r_h, cos_h = self._cast(
            target, T, self._rays_to_cast(target, T) if cull else None
        )
        ok = (cos_h >= self._cos_grazing) & (r_h >= c.min_range_m) & (r_h <= c.max_range_m)
        idx, face, r_h, cos_h = hit[ok], face[ok], r_h[ok], cos_h[ok]
        if c.error_model == "uniform":
            err = rng.uniform(-c.range_error_m, c.range_error_m, size=idx.size)
        else:
            err = c.range_error_m * rng.standard_normal(idx.size)
        r_meas = r_h + err
        positive = r_meas > 0
        if not positive.all():
            idx, r_h, cos_h, r_meas = (
                idx[positive],
                r_h[positive],
                cos_h[positive],
                r_meas[positive],
            )
            face = face[positive]
        dirs = self._dirs[idx]
        points = dirs * r_meas[:, None]
        organized = np.full((rows * cols, 3), np.nan)
        organized[idx] = points
        valid = np.zeros(rows * cols, dtype=bool)
        valid[idx] = True
        face_refl = target.reflectivity[face]
        n = idx.size
        return PointCloud(
            points=points,
            times=np.full(n, float(t)),
            subsystem=np.full(n, Subsystem.FLASH, dtype=np.int8),
            intensity=face_refl * cos_h,
            sigma=np.full(n, self.range_sigma),
            directions=dirs,
            true_points=dirs * r_h[:, None],
            spurious=np.zeros(n, dtype=bool),
            organized=organized.reshape(rows, cols, 3),
            valid_mask=valid.reshape(rows, cols),
            t_start=float(t),
            t_end=float(t),
        )


def _padded_bounds(target: TargetModel) -> tuple[FloatArray, FloatArray]:
    """The target's bounding box (body frame) grown by :data:`CULL_PAD_M`, cached on it."""

    def build() -> tuple[FloatArray, FloatArray]:
        b = target.bounds
        return b[0] - CULL_PAD_M, b[1] + CULL_PAD_M

    return target.cached(("flash_cull_bounds", CULL_PAD_M), build)  # type: ignore[no-any-return]


def _convex_hull(u: FloatArray, v: FloatArray) -> FloatArray:
    """(H, 2) counter-clockwise convex hull of a few points (Andrew's monotone chain)."""
    pts = sorted(set(zip(u.tolist(), v.tolist())))
    if len(pts) < 3:
        return np.asarray(pts, dtype=np.float64).reshape(-1, 2)

    def half(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
        out: list[tuple[float, float]] = []
        for q in points:
            while (
                len(out) >= 2
                and (
                    (out[-1][0] - out[-2][0]) * (q[1] - out[-2][1])
                    - (out[-1][1] - out[-2][1]) * (q[0] - out[-2][0])
                )
                <= 0
            ):
                out.pop()
            out.append(q)
        return out[:-1]

    return np.asarray(half(pts) + half(pts[::-1]), dtype=np.float64)


def _hull_chords(hull: FloatArray, heights: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Lowest and highest ``u`` of the convex polygon ``hull`` (H, 2) at each height ``v`` (R,),
    heights outside the polygon's taken at its top or bottom."""
    v = np.clip(heights, hull[:, 1].min(), hull[:, 1].max())[:, None]
    a, b = hull, np.roll(hull, -1, axis=0)
    dv = b[:, 1] - a[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (v - a[:, 1]) / dv  # (R, H); rounding is monotonic: in [0, 1] on a crossing edge
        u = np.where((t >= 0.0) & (t <= 1.0), a[:, 0] + t * (b[:, 0] - a[:, 0]), np.nan)
    at_vertex = np.where(v == a[:, 1], a[:, 0], np.nan)  # horizontal edges, single points
    u = np.concatenate([u, at_vertex], axis=1)
    return np.nanmin(u, axis=1), np.nanmax(u, axis=1)
