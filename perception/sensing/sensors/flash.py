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
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from perception.config import FlashLidarConfig
from perception.geometry import check_rigid
from perception.sensing.pointcloud import PointCloud, Subsystem
from perception.sensing.scan_patterns import angles_to_directions
from perception.sensing.sensors.raycast import cast_from_sensor
from perception.targets import TargetModel

FloatArray = npt.NDArray[np.float64]

__all__ = ["FlashLidar"]


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

    def capture(
        self,
        target: TargetModel,
        T_sensor_target: npt.ArrayLike,
        rng: np.random.Generator,
        t: float = 0.0,
    ) -> PointCloud:
        """One frame.

        Args:
            target: the target model.
            T_sensor_target: (4, 4) target pose in the sensor frame at time ``t``.
            rng: the only source of randomness.
            t: capture time [s].

        Returns:
            An organised cloud: ``organized`` (rows, cols, 3) with NaN at invalid pixels,
            ``valid_mask`` (rows, cols) and the valid points in row-major pixel order.
        """
        T = check_rigid(T_sensor_target, "T_sensor_target")
        if not math.isfinite(t):
            raise ValueError(f"t={t!r}; expected a finite time [s]")
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng={rng!r}; expected a numpy.random.Generator")
        c = self.config
        rows, cols = c.rows, c.cols
        hit, face, r_h, cos_h = cast_from_sensor(target, T, self._dirs, self._dirs32)
        ok = (cos_h >= self._cos_grazing) & (r_h >= c.min_range_m) & (r_h <= c.max_range_m)
        idx, face, r_h, cos_h = hit[ok], face[ok], r_h[ok], cos_h[ok]
        if c.error_model == "uniform":
            err = rng.uniform(-c.range_error_m, c.range_error_m, size=idx.size)
        else:
            err = c.range_error_m * rng.standard_normal(idx.size)
        r_meas = r_h + err
        positive = r_meas > 0
        if not positive.all():
            idx, r_h, cos_h, r_meas = idx[positive], r_h[positive], cos_h[positive], r_meas[positive]
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
