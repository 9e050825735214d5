"""The TriDAR hybrid scanning sensor: triangulation + time-of-flight through one pair of mirrors.

Seed 000 section 4.2 and 5.3.1: a flying spot steered by two mirrors along a scan pattern, one
sample at a time (~10 kHz); two ranging subsystems with their own models; range noise, laser
divergence, pointing resolution, and interactions with the target's shape and materials.

Per sample (all samples of a frame at once, one Embree call for every sub-ray):

1. **Pointing.** The beam leaves at the commanded angle plus jitter (``pointing.jitter_rad``,
   Gaussian per axis); the sensor reports the commanded angle quantised to
   ``pointing.resolution_rad``. Points lie along the *reported* direction.
2. **Motion.** Sample ``i`` is taken at ``t0 + pattern.times[i]`` and sees the target at its pose
   at that instant (:mod:`perception.sensing.sensors.motion`).
3. **Beam divergence.** The footprint (full angle ``beam.divergence_rad``) is sampled by a centre
   ray and ``beam.subrays - 1`` rays on its rim. Each sub-ray returns
   ``reflectivity * cos(incidence)`` of the face it hits: nothing beyond
   ``material.grazing_limit_deg``, and nothing from specular faces (MLI, polished metal) outside
   ``material.specular_cone_deg`` of normal incidence. The sample's signal is the mean over the
   sub-rays, so a partial footprint is dimmer. A footprint whose sub-ray ranges spread more than
   ``beam.mixed_range_tolerance_m`` straddles an edge (a mixed pixel).
4. **Triangulation** (``triangulation``): range = signal-weighted mean of the sub-ray ranges (on an
   edge the split spot gives a mixed range between the two surfaces); sigma = ``k r^2``; valid
   for ``min_range_m <= r <= max_range_m`` and ``signal >= min_signal``.
5. **Time of flight** (``tof``): the leading-edge detector fires on the first echo (the sub-rays
   within the mixed-range tolerance of the nearest one); range noise sigma constant plus
   ``bias_m``. Link budget: ``signal * power_fraction * (max_range_ref_m / r)^2 >= 1``, so dark
   surfaces and reduced power shorten the range. Invalid below ``min_range_m`` and, from surfaces
   brighter than ``saturation_reflectivity``, below ``saturation_range_m`` (detector saturation).
6. **Fusion.** Below ``transition_range_m`` triangulation is the primary; TOF fills its holes and
   replaces its outliers (triangulation and TOF disagreeing by more than 5 sigma, as on edges).
   At and above the transition only TOF is used. Each point records its subsystem.
7. **Faults** (:mod:`perception.sensing.sensors.faults`): occluder, spurious returns, dropouts, blackout.

Intensity is the signal ``reflectivity * cos(incidence)`` of the footprint (range independent).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from perception.config import SensorConfig
from perception.geometry import check_rigid
from perception.sensing.pointcloud import PointCloud, Subsystem
from perception.sensing.scan_patterns import (
    ScanPattern,
    angles_to_directions,
    make_pattern,
    steer_to_region,
)
from perception.sensing.sensors.faults import OCCLUDER_REFLECTIVITY, FaultInjector
from perception.sensing.sensors.motion import Motion, sample_poses
from perception.sensing.sensors.raycast import cast_from_sensor, cast_rays, sphere_hits
from perception.targets import RegionOfInterest, TargetModel

FloatArray = npt.NDArray[np.float64]

__all__ = ["TriDARSensor"]

#: TOF outlier gate on triangulation: |r_tri - r_tof| > OUTLIER_SIGMAS * combined sigma.
OUTLIER_SIGMAS = 5.0


class TriDARSensor:
    """Hybrid triangulation + TOF flying-spot scanner.

    Args:
        config: sensor settings; defaults as documented in :class:`~perception.config.SensorConfig`.
        motion_knots: poses sampled from a callable motion per frame (then interpolated).

    Example:
        >>> import numpy as np
        >>> from perception.geometry import make_T
        >>> from perception.targets import load_target
        >>> sensor = TriDARSensor()
        >>> cloud = sensor.scan(load_target("cygnss"), make_T(None, [0, 0, 10.0]),
        ...                     sensor.make_scan_pattern(0), np.random.default_rng(0))
    """

    def __init__(self, config: SensorConfig | None = None, motion_knots: int = 16) -> None:
        self.config = config or SensorConfig()
        if motion_knots < 2:
            raise ValueError(f"motion_knots={motion_knots}; expected >= 2")
        self.motion_knots = int(motion_knots)
        self.faults = FaultInjector(self.config.faults)
        self.frame_counter = 0
        self._subray_offsets = self._footprint_offsets()

    # -- configuration-derived values ------------------------------------------------------------
    @property
    def fov_rad(self) -> FloatArray:
        """(2,) full field of view (az, el) [rad]."""
        return np.radians(np.asarray(self.config.fov_deg, dtype=np.float64))

    @property
    def transition_range_m(self) -> float:
        """Triangulation/TOF switch range [m]."""
        return float(self.config.transition_range_m)  # type: ignore[arg-type]

    def tof_max_range(self, reflectivity: float, cos_incidence: float = 1.0) -> float:
        """Link-budget maximum TOF range [m] for a surface at a given incidence."""
        if not (0 <= reflectivity <= 1) or not (0 <= cos_incidence <= 1):
            raise ValueError(
                f"reflectivity={reflectivity}, cos_incidence={cos_incidence}; expected within [0, 1]"
            )
        tof = self.config.tof
        return tof.max_range_ref_m * math.sqrt(reflectivity * cos_incidence * tof.power_fraction)

    def range_sigma(self, ranges: npt.ArrayLike, subsystem: Subsystem) -> FloatArray:
        """1-sigma range noise [m] of a subsystem at ``ranges`` [m] under the configured model."""
        r = np.asarray(ranges, dtype=np.float64)
        if subsystem == Subsystem.TRIANGULATION:
            return self.config.triangulation.noise_k_per_m * r**2
        if subsystem == Subsystem.TOF:
            return np.full_like(r, self.config.tof.noise_sigma_m)
        raise ValueError(f"subsystem={subsystem!r}; expected TRIANGULATION or TOF")

    @property
    def subray_offsets(self) -> FloatArray:
        """(S, 2) (az, el) offsets [rad] of the footprint sub-rays (centre first, then the rim)."""
        return self._subray_offsets

    def _footprint_offsets(self) -> FloatArray:
        beam = self.config.beam
        offsets = np.zeros((beam.subrays, 2))
        if beam.subrays > 1:
            ang = 2 * np.pi * np.arange(beam.subrays - 1) / (beam.subrays - 1)
            rim = 0.5 * beam.divergence_rad
            offsets[1:, 0] = rim * np.cos(ang)
            offsets[1:, 1] = rim * np.sin(ang)
        return offsets

    def make_scan_pattern(
        self,
        frame_index: int = 0,
        T_sensor_target: npt.ArrayLike | None = None,
        region: RegionOfInterest | npt.ArrayLike | None = None,
        name: str | None = None,
        n_points: int | None = None,
        margin: float = 0.1,
    ) -> ScanPattern:
        """The configured pattern for a frame: phase advanced by ``scan.phase_step`` per frame.

        With ``T_sensor_target`` and ``region`` the pattern is steered onto the region (random
        access); otherwise it fills the field of view. Mirror acceleration is held to
        ``scan.max_mirror_accel_rad_s2``.
        """
        scan = self.config.scan
        pattern = name or scan.pattern
        n = n_points or scan.n_points
        phase = (frame_index * scan.phase_step) % (2 * np.pi)
        if region is not None and T_sensor_target is not None:
            return steer_to_region(
                pattern,
                T_sensor_target,
                region,
                self.fov_rad,
                margin=margin,
                n_points=n,
                phase=phase,
                sample_rate_hz=scan.sample_rate_hz,
                max_accel_rad_s2=scan.max_mirror_accel_rad_s2,
            )
        return make_pattern(
            pattern,
            n,
            self.fov_rad,
            phase=phase,
            sample_rate_hz=scan.sample_rate_hz,
            max_accel_rad_s2=scan.max_mirror_accel_rad_s2,
        )

    # -- the scan ----------------------------------------------------------------------------------
    def scan(
        self,
        target: TargetModel,
        T_sensor_target: npt.ArrayLike,
        pattern: ScanPattern,
        rng: np.random.Generator,
        motion: Motion | None = None,
        t0: float = 0.0,
        frame_index: int | None = None,
    ) -> PointCloud:
        """Scan the target along a pattern.

        Args:
            target: the target model.
            T_sensor_target: (4, 4) pose of the target at ``t0`` (used for every sample when
                ``motion`` is None).
            pattern: mirror angles and sample times; must lie within the field of view.
            rng: the only source of randomness.
            motion: None (static during the frame), a :class:`RelativeMotion`, an object with
                ``poses(times)`` or a callable ``t -> T_sensor_target`` (absolute time); when
                given, it sets the pose of every sample.
            t0: absolute time of the frame start [s].
            frame_index: frame number for the blackout fault; None uses (and advances) the
                sensor's own frame counter.

        Returns:
            The point cloud (possibly empty: target out of view, out of range or blacked out).

        Raises:
            ValueError: non-finite or non-rigid pose, non-finite ``t0``, a pattern outside the
                field of view or a bad motion.
        """
        T = check_rigid(T_sensor_target, "T_sensor_target")
        if not isinstance(pattern, ScanPattern):
            raise ValueError(f"pattern={type(pattern).__name__}; expected a ScanPattern")
        if not math.isfinite(t0):
            raise ValueError(f"t0={t0!r}; expected a finite time [s]")
        pattern.check_fov(self.fov_rad)
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng={rng!r}; expected a numpy.random.Generator")
        if frame_index is None:
            frame_index = self.frame_counter
        elif int(frame_index) < 0:
            raise ValueError(f"frame_index={frame_index}; expected >= 0")
        self.frame_counter = int(frame_index) + 1

        n = len(pattern)
        t_start, t_end = float(t0), float(t0) + pattern.duration
        if n == 0 or self.faults.blackout(int(frame_index)):
            return PointCloud.empty(t_start, t_end)
        times = t0 + pattern.times
        cfg = self.config

        # 1. Pointing: actual beam = commanded + jitter; reported = commanded, quantised.
        z = rng.standard_normal((n, 4))
        jit = cfg.pointing.jitter_rad
        az_a = pattern.az + jit * z[:, 0]
        el_a = pattern.el + jit * z[:, 1]
        res = cfg.pointing.resolution_rad
        if res > 0:
            az_r, el_r = np.round(pattern.az / res) * res, np.round(pattern.el / res) * res
        else:
            az_r, el_r = pattern.az, pattern.el
        reported = angles_to_directions(az_r, el_r)

        # 3. Footprint sub-rays (S, N, 3), sensor frame: sub-ray major, so the footprint
        # statistics below reduce over contiguous rows rather than along a short inner axis.
        off = self._subray_offsets
        s = off.shape[0]
        dirs_s = angles_to_directions(az_a + off[:, 0, None], el_a + off[:, 1, None])
        flat_s = dirs_s.reshape(-1, 3)

        # 2. Rays into the target frame, each with its sample's pose.
        if motion is None:
            hit_i, f_h, r_h, c_h = cast_from_sensor(target, T, flat_s)
            face = np.full(n * s, -1, dtype=np.int64)
            r_k = np.full(n * s, np.nan)
            cos_k = np.full(n * s, np.nan)
            face[hit_i], r_k[hit_i], cos_k[hit_i] = f_h, r_h, c_h
        else:
            Ts = sample_poses(motion, times, float(t0), self.motion_knots)
            R, p = Ts[:, :3, :3], Ts[:, :3, 3]
            # R^T x per sample as row-vector products (batched matmul is ~6x einsum's speed here).
            o_n = -np.matmul(p[:, None, :], R)[:, 0]
            origins = np.broadcast_to(o_n, (s, n, 3)).reshape(-1, 3)
            dirs_t = np.matmul(dirs_s.transpose(1, 0, 2), R).transpose(1, 0, 2).reshape(-1, 3)
            face, r_k, cos_k = cast_rays(target, origins, dirs_t)

        # Material response of each sub-ray.
        mat = cfg.material
        hit = face >= 0
        fidx = np.where(hit, face, 0)
        refl = target.reflectivity[fidx]
        spec = target.specular[fidx]
        cos_k = np.where(hit, cos_k, 0.0)
        returns = hit & (cos_k >= math.cos(math.radians(mat.grazing_limit_deg)))
        returns &= ~spec | (cos_k >= math.cos(math.radians(mat.specular_cone_deg)))
        w = np.where(returns, refl * cos_k, 0.0)
        occl = cfg.faults.occluder
        from_occluder = np.zeros(r_k.shape, dtype=bool)
        if occl is not None:
            r_occ = sphere_hits(flat_s, occl.center_m, occl.radius_m)
            from_occluder = np.isfinite(r_occ) & ~(returns & (r_k < r_occ))
            c_occ = occl.center_m
            if np.any(from_occluder):
                # Occluder surface normal at the hit: from the centre to the hit point.
                pts = flat_s[from_occluder] * r_occ[from_occluder, None]
                nrm = (pts - np.asarray(c_occ)) / occl.radius_m
                cos_o = -np.einsum("ij,ij->i", nrm, flat_s[from_occluder])
                r_k = r_k.copy()
                r_k[from_occluder] = r_occ[from_occluder]
                ok_o = cos_o >= math.cos(math.radians(mat.grazing_limit_deg))
                w[from_occluder] = np.where(ok_o, OCCLUDER_REFLECTIVITY * cos_o, 0.0)
                returns = returns.copy()
                returns[from_occluder] = ok_o
        r_k = np.where(returns, r_k, 0.0).reshape(s, n)
        returns = returns.reshape(s, n)
        w = w.reshape(s, n)
        any_ret = returns.any(axis=0)

        # Footprint statistics: signal, mean range, first echo, spread.
        w_sum = w.sum(axis=0)
        signal = w_sum / s
        safe_w = np.where(w_sum > 0, w_sum, 1.0)
        r_mean = (w * r_k).sum(axis=0) / safe_w
        r_min = np.where(returns, r_k, np.inf).min(axis=0)
        tol = cfg.beam.mixed_range_tolerance_m
        first = returns & (r_k <= r_min + tol)
        w_first = np.where(first, w, 0.0)
        wf_sum = w_first.sum(axis=0)
        signal_first = wf_sum / s
        r_first = (w_first * r_k).sum(axis=0) / np.where(wf_sum > 0, wf_sum, 1.0)
        occ_share = (
            np.where(from_occluder.reshape(s, n), w, 0.0).sum(axis=0) / safe_w
            if occl is not None
            else np.zeros(n)
        )

        # 4. Triangulation.
        tri = cfg.triangulation
        tri_ok = any_ret & (signal >= tri.min_signal)
        tri_ok &= (r_mean >= tri.min_range_m) & (r_mean <= tri.max_range_m)
        sig_tri = tri.noise_k_per_m * r_mean**2
        r_tri = r_mean + sig_tri * z[:, 2]

        # 5. TOF.
        tof = cfg.tof
        safe_rf = np.where(any_ret, r_first, 1.0)
        link = signal_first * tof.power_fraction * (tof.max_range_ref_m / safe_rf) ** 2
        tof_ok = any_ret & (link >= 1.0) & (r_first >= tof.min_range_m)
        tof_ok &= ~((r_first < tof.saturation_range_m) & (signal_first > tof.saturation_reflectivity))
        r_tof = r_first + tof.bias_m + tof.noise_sigma_m * z[:, 3]

        # 6. Fusion.
        transition = self.transition_range_m
        gate = OUTLIER_SIGMAS * np.sqrt(sig_tri**2 + tof.noise_sigma_m**2) + abs(tof.bias_m)
        tri_outlier = tri_ok & tof_ok & (np.abs(r_tri - r_tof) > gate)
        below = np.where(tri_ok, r_tri, r_tof) < transition
        use_tri = tri_ok & below & ~tri_outlier
        use_tof = tof_ok & ~use_tri
        keep = use_tri | use_tof
        r_meas = np.where(use_tri, r_tri, r_tof)
        r_true = np.where(use_tri, r_mean, r_first)
        subsystem = np.where(use_tri, Subsystem.TRIANGULATION, Subsystem.TOF).astype(np.int8)
        sigma = np.where(use_tri, sig_tri, tof.noise_sigma_m)
        intensity = np.where(use_tri, signal, signal_first)
        spurious = occ_share > 0.5

        # 7. Faults: stray-light returns replace samples, dropouts remove them.
        dropped, glint, r_glint = self.faults.draw(
            rng, n, r_meas[keep & ~spurious], transition
        )
        if glint.any():
            g_tri = r_glint < transition
            r_meas = np.where(glint, r_glint, r_meas)
            subsystem = np.where(
                glint, np.where(g_tri, Subsystem.TRIANGULATION, Subsystem.TOF), subsystem
            ).astype(np.int8)
            sigma = np.where(
                glint, np.where(g_tri, tri.noise_k_per_m * r_glint**2, tof.noise_sigma_m), sigma
            )
            intensity = np.where(glint, 1.0, intensity)
            spurious = spurious | glint
            keep = keep | glint
        keep &= ~dropped & (r_meas > 0)
        idx = np.flatnonzero(keep)
        if idx.size == 0:
            return PointCloud.empty(t_start, t_end)

        centre_dirs = dirs_s[0, idx]
        true_pts = centre_dirs * r_true[idx, None]
        true_pts[glint[idx]] = np.nan  # stray light has no surface point
        return PointCloud(
            points=reported[idx] * r_meas[idx, None],
            times=times[idx],
            subsystem=subsystem[idx],
            intensity=intensity[idx],
            sigma=sigma[idx],
            directions=reported[idx],
            true_points=true_pts,
            spurious=spurious[idx],
            t_start=t_start,
            t_end=t_end,
        )
