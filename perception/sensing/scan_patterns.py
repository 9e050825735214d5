"""TriDAR scan patterns (seed 000 section 4.3, Fig. 7) and area-of-interest steering.

A :class:`ScanPattern` is a sequence of mirror angles with a sample time for every point. The
flying-spot scanner collects one sample at a time (~10,000 samples/s), so ~1,000 points take
~0.1 s. Patterns are smooth closed-form waveforms: the mirrors accelerate and decelerate
sinusoidally (bounded acceleration, checked with :meth:`ScanPattern.peak_acceleration`).

Angle convention (used everywhere in this package): ``az`` and ``el`` [rad] are the angles of the
ray projected onto the sensor x-z and y-z planes, ``az`` positive toward +x (right) and ``el``
positive toward -y (up)::

    direction ~ (tan az, -tan el, 1)

so a rectangular field of view is ``|az| <= fov_az / 2`` and ``|el| <= fov_el / 2``, and a pinhole
grid of pixels (the flash LiDAR) has the same angles as a pattern.

Density profiles (seed 000 Fig. 7 text):

- ``lissajous``: two sinusoids of neighbouring frequencies; high density in the corners and along
  the edges, low in the centre (monitoring transitions at the edges).
- ``rosette``: sum of two counter-rotating circles (Risley-prism rosette); every petal passes
  through the centre, so density is highest at the centre and lowest at the periphery.
- ``spiral``: constant tangential speed, equal radial spacing between turns and equal angular
  spacing of samples along each turn: area-uniform density (surface digitisation, inspection).
  It runs outward; the retrace to the centre happens between frames.
- ``raster``: a sinusoidal fast axis and a constant-rate slow axis (inspection).

The ``phase`` [rad] changes the waveform from frame to frame to increase the effective coverage:
the Lissajous x phase, the rotation of the rosette and of the spiral, and the fast-axis phase of
the raster (its zig-zag lines cross new ground).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from perception.targets import RegionOfInterest

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "PATTERNS",
    "ScanPattern",
    "angles_to_directions",
    "as_fov",
    "directions_to_angles",
    "lissajous",
    "make_pattern",
    "raster",
    "region_angular_box",
    "rosette",
    "spiral",
    "steer_to_region",
]

DEFAULT_SAMPLE_RATE_HZ = 10_000.0


def as_fov(fov_rad: float | npt.ArrayLike, name: str = "fov_rad") -> FloatArray:
    """(2,) full field of view (az, el) [rad] from a scalar or a pair; must lie in (0, pi)."""
    vals = np.asarray(fov_rad, dtype=np.float64).reshape(-1).tolist()
    if len(vals) == 1:
        vals = vals * 2
    # (plain floats: this runs several times per frame on two numbers)
    if len(vals) != 2 or not all(0.0 < v < math.pi for v in vals):
        raise ValueError(f"{name}={fov_rad!r}; expected one or two full angles in (0, pi) [rad]")
    return np.array(vals)


def angles_to_directions(az: npt.ArrayLike, el: npt.ArrayLike) -> FloatArray:
    """Unit ray directions (N, 3), sensor frame, from mirror angles (N,) [rad] (module convention)."""
    az, el = np.broadcast_arrays(np.asarray(az, dtype=np.float64), np.asarray(el, dtype=np.float64))
    x = np.tan(az)
    y = np.tan(el)
    inv = 1.0 / np.sqrt(x * x + y * y + 1.0)
    d = np.empty((*az.shape, 3))
    d[..., 0] = x * inv
    d[..., 1] = -y * inv
    d[..., 2] = inv
    return d


def directions_to_angles(directions: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Inverse of :func:`angles_to_directions` for rays with z > 0: (az, el) [rad]."""
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    return np.arctan2(d[:, 0], d[:, 2]), np.arctan2(-d[:, 1], d[:, 2])


@dataclass(frozen=True)
class ScanPattern:
    """Mirror angles and sample times of one frame.

    Attributes:
        az: (N,) azimuth [rad], toward +x (right).
        el: (N,) elevation [rad], toward -y (up).
        times: (N,) sample times [s] relative to the frame start.
        name: pattern family (``lissajous``, ``rosette``, ``spiral``, ``raster`` or ``custom``).
        phase: waveform phase [rad] of this frame.
        sample_rate_hz: samples per second.
    """

    az: FloatArray
    el: FloatArray
    times: FloatArray
    name: str = "custom"
    phase: float = 0.0
    sample_rate_hz: float = DEFAULT_SAMPLE_RATE_HZ

    def __post_init__(self) -> None:
        az = np.asarray(self.az, dtype=np.float64).reshape(-1)
        el = np.asarray(self.el, dtype=np.float64).reshape(-1)
        times = np.asarray(self.times, dtype=np.float64).reshape(-1)
        if not (az.shape == el.shape == times.shape):
            raise ValueError(
                f"ScanPattern az {az.shape}, el {el.shape} and times {times.shape}; expected equal"
            )
        for name, arr in (("az", az), ("el", el), ("times", times)):
            if not np.isfinite(arr).all():
                raise ValueError(f"ScanPattern.{name} has non-finite entries; expected finite angles")
        if az.size and max(np.abs(az).max(), np.abs(el).max()) >= np.pi / 2:
            raise ValueError("ScanPattern angles must lie within (-pi/2, pi/2) [rad]")
        if times.size > 1 and (times[1:] < times[:-1]).any():
            raise ValueError("ScanPattern.times must be non-decreasing [s]")
        if not (math.isfinite(self.sample_rate_hz) and self.sample_rate_hz > 0):
            raise ValueError(f"sample_rate_hz={self.sample_rate_hz}; expected > 0 [Hz]")
        for arr in (az, el, times):
            arr.setflags(write=False)
        object.__setattr__(self, "az", az)
        object.__setattr__(self, "el", el)
        object.__setattr__(self, "times", times)

    def __len__(self) -> int:
        return int(self.az.shape[0])

    @property
    def duration(self) -> float:
        """Frame duration [s]: ``n_points / sample_rate_hz``."""
        return len(self) / float(self.sample_rate_hz)

    def directions(self) -> FloatArray:
        """(N, 3) unit ray directions in the sensor frame."""
        return angles_to_directions(self.az, self.el)

    def angular_box(self) -> tuple[FloatArray, FloatArray]:
        """Lower and upper (az, el) corners [rad] of the pattern's bounding box."""
        return (
            np.array([self.az.min(), self.el.min()]),
            np.array([self.az.max(), self.el.max()]),
        )

    def peak_acceleration(self) -> float:
        """Largest mirror angular acceleration [rad/s^2] of either axis, by finite differences."""
        if len(self) < 3:
            return 0.0
        return _peak_acceleration(self.az, self.el, _step_products(self.times))

    def check_fov(self, fov_rad: float | npt.ArrayLike, tol: float = 1e-9) -> None:
        """Raise ``ValueError`` naming ``pattern`` if any angle lies outside the field of view."""
        half = 0.5 * as_fov(fov_rad)
        if len(self) == 0:
            return
        worst_az = float(np.abs(self.az).max())
        worst_el = float(np.abs(self.el).max())
        if worst_az > half[0] + tol or worst_el > half[1] + tol:
            raise ValueError(
                f"pattern {self.name!r} reaches |az|={worst_az:.4f}, |el|={worst_el:.4f} rad; "
                f"expected within the field of view +-({half[0]:.4f}, {half[1]:.4f}) rad"
            )

    def check_smooth(self, max_accel_rad_s2: float) -> None:
        """Raise ``ValueError`` when the mirror acceleration exceeds ``max_accel_rad_s2``."""
        peak = self.peak_acceleration()
        if peak > max_accel_rad_s2:
            raise ValueError(
                f"pattern {self.name!r} needs {peak:.4g} rad/s^2 of mirror acceleration; "
                f"expected <= max_accel_rad_s2={max_accel_rad_s2:.4g}"
            )

    def scaled(self, center: npt.ArrayLike, half_extent: npt.ArrayLike) -> ScanPattern:
        """The same waveform mapped affinely from its bounding box onto ``center +- half_extent``."""
        lo, hi = self.angular_box()
        c0 = 0.5 * (lo + hi)
        h0 = np.maximum(0.5 * (hi - lo), 1e-12)
        c = np.asarray(center, dtype=np.float64).reshape(2)
        h = np.asarray(half_extent, dtype=np.float64).reshape(2)
        return replace(
            self,
            az=c[0] + (self.az - c0[0]) * (h[0] / h0[0]),
            el=c[1] + (self.el - c0[1]) * (h[1] / h0[1]),
        )


# ---------------------------------------------------------------------------------------------
# Normalised waveforms: s in [0, 1) over the frame -> (u, v) in [-1, 1]^2
# ---------------------------------------------------------------------------------------------
def _lissajous_uv(s: FloatArray, phase: float, k: int) -> tuple[FloatArray, FloatArray]:
    # k and k + 1 cycles per frame: coprime, so the figure closes on itself at the frame end.
    return np.sin(2 * np.pi * k * s + phase), np.sin(2 * np.pi * (k + 1) * s)


def _rosette_uv(s: FloatArray, phase: float, k: int) -> tuple[FloatArray, FloatArray]:
    # z = (e^{i a w} + e^{-i b w}) / 2 with a = k + 1, b = k: 2k + 1 petals, all through the centre.
    w = 2 * np.pi * s
    z = 0.5 * (np.exp(1j * (k + 1) * w) + np.exp(-1j * k * w)) * np.exp(1j * phase)
    return z.real, z.imag


def _spiral_uv(s: FloatArray, phase: float, k: int) -> tuple[FloatArray, FloatArray]:
    # Constant tangential speed and equal radial spacing: r^2 linear in time (area-uniform).
    # The inner radius is half a turn spacing, which bounds the centripetal acceleration.
    r0 = 1.0 / (2 * k + 1)
    r = np.sqrt(r0**2 + (1.0 - r0**2) * s)
    theta = 2 * np.pi * k * (r - r0) / (1.0 - r0) + phase
    return r * np.cos(theta), r * np.sin(theta)


def _raster_uv(s: FloatArray, phase: float, k: int) -> tuple[FloatArray, FloatArray]:
    # k lines: the fast axis does one half sine period per line while the slow axis moves at a
    # constant rate (zig-zag lines); the phase shifts the fast axis so the lines cross new ground.
    return -np.cos(np.pi * k * s + phase), 2.0 * s - 1.0 + 1.0 / len(s)


_Waveform = Callable[[FloatArray, float, int], tuple[FloatArray, FloatArray]]

#: name -> (normalised waveform, default cycles for n points, smallest meaningful cycles)
_WAVEFORMS: dict[str, tuple[_Waveform, Callable[[int], int], int]] = {
    "lissajous": (_lissajous_uv, lambda n: max(2, round(0.3 * math.sqrt(n))), 1),
    "rosette": (_rosette_uv, lambda n: max(2, round(0.27 * math.sqrt(n))), 1),
    "spiral": (_spiral_uv, lambda n: max(2, round(0.19 * math.sqrt(n))), 1),
    "raster": (_raster_uv, lambda n: max(2, round(0.63 * math.sqrt(n))), 2),
}

#: Patterns that fill an ellipse rather than their bounding box.
_ROUND = frozenset({"rosette", "spiral"})

#: Names accepted by :func:`make_pattern`.
PATTERNS: tuple[str, ...] = tuple(_WAVEFORMS)


def _generate(
    name: str,
    n_points: int,
    fov_rad: float | npt.ArrayLike,
    phase: float,
    sample_rate_hz: float,
    cycles: int | None,
    max_accel_rad_s2: float | None,
    center: npt.ArrayLike | None = None,
) -> ScanPattern:
    if isinstance(n_points, bool) or int(n_points) != n_points or int(n_points) < 4:
        raise ValueError(f"n_points={n_points!r}; expected an integer >= 4")
    n = int(n_points)
    if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
        raise ValueError(f"sample_rate_hz={sample_rate_hz!r}; expected a finite rate > 0 [Hz]")
    if not math.isfinite(phase):
        raise ValueError(f"phase={phase!r}; expected a finite angle [rad]")
    if max_accel_rad_s2 is not None and not (
        math.isfinite(max_accel_rad_s2) and max_accel_rad_s2 > 0
    ):
        raise ValueError(f"max_accel_rad_s2={max_accel_rad_s2!r}; expected > 0 [rad/s^2]")
    half = 0.5 * as_fov(fov_rad)
    c = np.zeros(2) if center is None else np.asarray(center, dtype=np.float64).reshape(2)
    wave, default_cycles, min_cycles = _WAVEFORMS[name]
    k = default_cycles(n) if cycles is None else int(cycles)
    if k < min_cycles:
        raise ValueError(f"cycles={cycles!r} for {name}; expected >= {min_cycles}")
    times, s, dt2 = _sample_grid(n, float(sample_rate_hz))
    while True:
        u, v = wave(s, float(phase), k)
        az = c[0] + half[0] * u
        el = c[1] + half[1] * v
        fits = max_accel_rad_s2 is None or _peak_acceleration(az, el, dt2) <= max_accel_rad_s2
        if fits or k <= min_cycles:
            pattern = ScanPattern(az=az, el=el, times=times, name=name, phase=float(phase),
                                  sample_rate_hz=float(sample_rate_hz))
            if not fits:
                pattern.check_smooth(max_accel_rad_s2)  # raises with the numbers
            return pattern
        # Acceleration grows ~ k^2 (k^3 for the spiral centre): shrink the waveform until it fits.
        k -= 1


@functools.lru_cache(maxsize=16)
def _sample_grid(n: int, sample_rate_hz: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Sample times [s], waveform parameter ``s`` in [0, 1) and the finite-difference ``dt^2`` of
    :meth:`ScanPattern.peak_acceleration` for ``n`` samples (read-only, shared across frames)."""
    times = np.arange(n, dtype=np.float64) / sample_rate_hz
    s = np.arange(n, dtype=np.float64) / n
    dt2 = _step_products(times)
    for arr in (times, s, dt2):
        arr.setflags(write=False)
    return times, s, dt2


def _step_products(times: FloatArray) -> FloatArray:
    """``dt_i dt_(i+1)`` of consecutive sample steps (inf where a step is zero): the denominator
    of the second differences in :func:`_peak_acceleration`."""
    dt = np.diff(times)
    dt2 = dt[:-1] * dt[1:]
    return np.where(dt2 > 0, dt2, np.inf)


def _peak_acceleration(az: FloatArray, el: FloatArray, dt2: FloatArray) -> float:
    """:meth:`ScanPattern.peak_acceleration` of angles ``az``, ``el`` (same arithmetic)."""
    if az.size < 3:
        return 0.0
    # np.diff(x, 2), same arithmetic, without its per-call overhead.
    d2az = (az[2:] - az[1:-1]) - (az[1:-1] - az[:-2])
    d2el = (el[2:] - el[1:-1]) - (el[1:-1] - el[:-2])
    return float(max((np.abs(d2az) / dt2).max(), (np.abs(d2el) / dt2).max()))


def lissajous(
    n_points: int,
    fov_rad: float | npt.ArrayLike,
    phase: float = 0.0,
    sample_rate_hz: float = DEFAULT_SAMPLE_RATE_HZ,
    cycles: int | None = None,
    max_accel_rad_s2: float | None = None,
) -> ScanPattern:
    """Lissajous pattern: ``az ~ sin(2 pi k s + phase)``, ``el ~ sin(2 pi (k + 1) s)``.

    Args:
        n_points: samples in the frame (>= 4).
        fov_rad: full angular size (az, el) or one angle for both [rad]; the pattern fills it.
        phase: x phase [rad]; advance it frame to frame to cover new ground.
        sample_rate_hz: samples per second [Hz].
        cycles: ``k``; default ~0.3 sqrt(n_points) (9 for 1,000 points).
        max_accel_rad_s2: when given, ``k`` is lowered until the mirrors stay within this
            acceleration [rad/s^2]; ``ValueError`` if even the simplest waveform exceeds it.

    Returns:
        The pattern, centred on the boresight.
    """
    return _generate("lissajous", n_points, fov_rad, phase, sample_rate_hz, cycles, max_accel_rad_s2)


def rosette(
    n_points: int,
    fov_rad: float | npt.ArrayLike,
    phase: float = 0.0,
    sample_rate_hz: float = DEFAULT_SAMPLE_RATE_HZ,
    cycles: int | None = None,
    max_accel_rad_s2: float | None = None,
) -> ScanPattern:
    """Rosette pattern with ``2 k + 1`` petals through the centre, rotated by ``phase``.

    Arguments as :func:`lissajous`; ``cycles`` defaults to ~0.27 sqrt(n_points) (17 petals for
    1,000 points).
    """
    return _generate("rosette", n_points, fov_rad, phase, sample_rate_hz, cycles, max_accel_rad_s2)


def spiral(
    n_points: int,
    fov_rad: float | npt.ArrayLike,
    phase: float = 0.0,
    sample_rate_hz: float = DEFAULT_SAMPLE_RATE_HZ,
    cycles: int | None = None,
    max_accel_rad_s2: float | None = None,
) -> ScanPattern:
    """Outward area-uniform spiral with ``k`` turns, rotated by ``phase``.

    Arguments as :func:`lissajous`; ``cycles`` (turns) defaults to ~0.19 sqrt(n_points) (6 for
    1,000 points).
    """
    return _generate("spiral", n_points, fov_rad, phase, sample_rate_hz, cycles, max_accel_rad_s2)


def raster(
    n_points: int,
    fov_rad: float | npt.ArrayLike,
    phase: float = 0.0,
    sample_rate_hz: float = DEFAULT_SAMPLE_RATE_HZ,
    cycles: int | None = None,
    max_accel_rad_s2: float | None = None,
) -> ScanPattern:
    """Sinusoidal raster with ``k`` lines (fast axis az, slow axis el, bottom to top).

    Arguments as :func:`lissajous`; ``cycles`` (lines) defaults to ~0.63 sqrt(n_points) (20 for
    1,000 points).
    """
    return _generate("raster", n_points, fov_rad, phase, sample_rate_hz, cycles, max_accel_rad_s2)


def make_pattern(
    name: str,
    n_points: int,
    fov_rad: float | npt.ArrayLike,
    phase: float = 0.0,
    sample_rate_hz: float = DEFAULT_SAMPLE_RATE_HZ,
    cycles: int | None = None,
    max_accel_rad_s2: float | None = None,
    center: npt.ArrayLike | None = None,
) -> ScanPattern:
    """A pattern by name, optionally centred off-boresight at ``center`` (az, el) [rad].

    ``fov_rad`` is then the full size of the scanned box, not of the sensor field of view.
    """
    if name not in _WAVEFORMS:
        raise ValueError(f"pattern name={name!r}; expected one of {', '.join(PATTERNS)}")
    return _generate(
        name, n_points, fov_rad, phase, sample_rate_hz, cycles, max_accel_rad_s2, center
    )


# ---------------------------------------------------------------------------------------------
# Area-of-interest steering ("random access", seed 000 section 4.1)
# ---------------------------------------------------------------------------------------------
def region_angular_box(
    T_sensor_target: npt.ArrayLike,
    region: RegionOfInterest | npt.ArrayLike,
    min_depth_m: float = 1e-3,
) -> tuple[FloatArray, FloatArray] | None:
    """Angular bounding box (az, el) [rad] of a region seen from the sensor.

    The perspective image of a convex box in front of the sensor is the convex hull of the images
    of its corners, so the box of the corner angles is exact.

    Args:
        T_sensor_target: (4, 4) predicted pose of the target in the sensor frame.
        region: a :class:`RegionOfInterest` or (M, 3) points [m], target frame.
        min_depth_m: corners closer than this to the sensor plane (z) count as beside/behind it.

    Returns:
        ``(lo, hi)`` (2,) arrays, or ``None`` when every corner is behind the sensor. When the
        region straddles the sensor plane the box is unbounded (``-inf``/``inf``).
    """
    T = np.asarray(T_sensor_target, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(
            f"T_sensor_target has shape {T.shape} or non-finite entries; expected a finite (4, 4)"
        )
    corners = region.corners() if isinstance(region, RegionOfInterest) else region
    pts = np.asarray(corners, dtype=np.float64).reshape(-1, 3)
    if pts.shape[0] == 0 or not np.all(np.isfinite(pts)):
        raise ValueError("corners_target must be a non-empty finite (M, 3) array [m]")
    p = pts @ T[:3, :3].T + T[:3, 3]
    front = p[:, 2] > min_depth_m
    if not front.any():
        return None
    if not front.all():
        return np.array([-np.inf, -np.inf]), np.array([np.inf, np.inf])
    az = np.arctan2(p[:, 0], p[:, 2])
    el = np.arctan2(-p[:, 1], p[:, 2])
    return np.array([az.min(), el.min()]), np.array([az.max(), el.max()])


def steer_to_region(
    pattern_or_name: ScanPattern | str,
    T_sensor_target: npt.ArrayLike,
    region: RegionOfInterest | npt.ArrayLike,
    fov_rad: float | npt.ArrayLike,
    margin: float = 0.1,
    n_points: int | None = None,
    phase: float = 0.0,
    sample_rate_hz: float = DEFAULT_SAMPLE_RATE_HZ,
    max_accel_rad_s2: float | None = None,
    min_half_angle_rad: float = 1e-3,
) -> ScanPattern:
    """Scale and offset a pattern so that it covers just a region of the target.

    The region's angular box (grown by ``margin``) is the scanned box of Lissajous and raster
    patterns; rosette and spiral fill the ellipse circumscribing it. The result is clipped to the
    field of view.

    Args:
        pattern_or_name: a :class:`ScanPattern` (its waveform is remapped affinely) or a pattern
            name (a new waveform is generated for the region, so its mirror acceleration shrinks
            with the region).
        T_sensor_target: (4, 4) predicted target pose in the sensor frame.
        region: a :class:`RegionOfInterest` or its corners (M, 3) [m], target frame.
        fov_rad: sensor field of view (az, el) or one angle [rad]; the result is clipped to it.
        margin: fractional growth of the region's angular half-size (>= 0) for prediction error.
        n_points: samples when generating by name (default 1,000).
        phase, sample_rate_hz, max_accel_rad_s2: as in :func:`make_pattern` (name only).
        min_half_angle_rad: smallest half-size of the scanned box [rad] (a far target).

    Returns:
        The steered pattern, inside the field of view.

    Raises:
        ValueError: bad arguments, or the region lies entirely behind the sensor or outside the
            field of view (nothing to steer onto).
    """
    if not (math.isfinite(margin) and margin >= 0):
        raise ValueError(f"margin={margin!r}; expected a finite fraction >= 0")
    if not (math.isfinite(min_half_angle_rad) and min_half_angle_rad > 0):
        raise ValueError(f"min_half_angle_rad={min_half_angle_rad!r}; expected > 0 [rad]")
    half_fov = 0.5 * as_fov(fov_rad)
    box = region_angular_box(T_sensor_target, region)
    if box is None:
        raise ValueError("T_sensor_target puts the region entirely behind the sensor; nothing to scan")
    lo, hi = box
    name = pattern_or_name.name if isinstance(pattern_or_name, ScanPattern) else pattern_or_name
    if np.all(np.isfinite(lo)):
        c = 0.5 * (lo + hi)
        h = np.maximum(0.5 * (hi - lo) * (1.0 + margin), min_half_angle_rad)
        if name in _ROUND:
            h = h * math.sqrt(2.0)  # the pattern's ellipse circumscribes the region's box
        lo, hi = c - h, c + h
    lo = np.maximum(lo, -half_fov)
    hi = np.minimum(hi, half_fov)
    if np.any(hi <= lo):
        raise ValueError(
            f"T_sensor_target puts the region at az/el box {box[0]}..{box[1]} rad, outside the "
            f"field of view +-{half_fov} rad"
        )
    center = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    if isinstance(pattern_or_name, ScanPattern):
        return pattern_or_name.scaled(center, half)
    return make_pattern(
        pattern_or_name,
        1000 if n_points is None else n_points,
        2.0 * half,
        phase=phase,
        sample_rate_hz=sample_rate_hz,
        max_accel_rad_s2=max_accel_rad_s2,
        center=center,
    )
