"""Configuration of the sensors: the TriDAR hybrid scanner (triangulation, time of flight, beam,
pointing, material response, faults, scan pattern), the flash LiDAR of seed 003 and the passive
thermal infrared imager (seed 000's long-range bearing sensor)."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import Field, StrictBool, model_validator

from perception.config.types import (
    MAX_COUNT,
    MAX_SIGMA_M,
    FieldOfView,
    Float,
    Int,
    NonNegRange,
    Range,
    Sigma,
    Size,
    SmallAngle,
    StrictModel,
    UnitFloat,
    Vec3,
)


class TriangulationConfig(StrictModel):
    """Triangulation subsystem: range noise sigma = k r^2, valid up to ``max_range_m``."""

    noise_k_per_m: UnitFloat = Field(5e-4, description="sigma = k * r^2 [1/m]")
    min_range_m: NonNegRange = 0.3
    max_range_m: Range = 20.0
    min_signal: UnitFloat = Field(
        0.02, description="reflectivity * cos(incidence) below which the spot is too dim to locate"
    )

    @model_validator(mode="after")
    def _ranges(self) -> TriangulationConfig:
        if self.min_range_m >= self.max_range_m:
            raise ValueError(
                f"min_range_m={self.min_range_m} must be below max_range_m={self.max_range_m}"
            )
        return self


class TOFConfig(StrictModel):
    """Pulsed time-of-flight LIDAR: constant noise + bias, link-budget maximum range.

    The received signal is ``reflectivity * cos(incidence) * power_fraction * (R_ref / r)^2``
    against a detection threshold of 1: ``max_range_ref_m`` is the range at which a white
    (reflectivity 1) surface at normal incidence at full power just reaches the threshold.
    Returns closer than ``saturation_range_m`` from surfaces brighter than
    ``saturation_reflectivity`` saturate the detector and are invalid.
    """

    noise_sigma_m: Sigma = 0.025
    bias_m: Annotated[Float, Field(ge=-MAX_SIGMA_M, le=MAX_SIGMA_M)] = 0.005
    max_range_ref_m: Range = 3000.0
    power_fraction: Annotated[Float, Field(gt=0, le=1)] = 1.0
    saturation_range_m: NonNegRange = 2.0
    saturation_reflectivity: UnitFloat = 0.3
    min_range_m: NonNegRange = 0.5


class BeamConfig(StrictModel):
    """Laser footprint: full-angle divergence and the sub-rays that sample it."""

    divergence_rad: SmallAngle = 5e-4
    subrays: Annotated[Int, Field(ge=1, le=64)] = 5
    mixed_range_tolerance_m: Size = Field(
        0.05, description="sub-ray ranges spread more than this -> mixed pixel (edge)"
    )


class PointingConfig(StrictModel):
    """Scanning-mirror pointing: angle quantisation and random jitter."""

    resolution_rad: SmallAngle = 2e-5
    jitter_rad: SmallAngle = 1e-5


class MaterialResponseConfig(StrictModel):
    """How surfaces return light: grazing dropout and the specular acceptance cone."""

    grazing_limit_deg: Annotated[Float, Field(gt=0, le=90)] = 80.0
    specular_cone_deg: Annotated[Float, Field(gt=0, le=90)] = 5.0


class OccluderConfig(StrictModel):
    """A sphere in the sensor frame that blocks rays (an arm, a boom, a visiting vehicle)."""

    center_m: Vec3
    radius_m: Size


class FaultsConfig(StrictModel):
    """Fault and environment injection (all off by default)."""

    dropout_prob: UnitFloat = 0.0
    spurious_prob: UnitFloat = Field(
        0.0, description="per-sample probability of a stray-light return"
    )
    blackout_start_frame: Annotated[Int, Field(ge=0, le=MAX_COUNT)] | None = None
    blackout_frames: Annotated[Int, Field(ge=0, le=MAX_COUNT)] = 0
    occluder: OccluderConfig | None = None


class ScanConfig(StrictModel):
    """Scan pattern selection and mirror limits."""

    pattern: Literal["lissajous", "rosette", "spiral", "raster"] = "rosette"
    n_points: Annotated[Int, Field(ge=4, le=200_000)] = 1000
    sample_rate_hz: Annotated[Float, Field(gt=0, le=1e9)] = 10_000.0
    phase_step: Annotated[Float, Field(ge=-2 * math.pi, le=2 * math.pi)] = Field(
        0.37, description="pattern phase advance per frame [rad]"
    )
    max_mirror_accel_rad_s2: Annotated[Float, Field(gt=0, le=1e9)] = Field(
        200_000.0,
        description="optical-angle limit; ~1,000-point patterns over 30 deg in 0.1 s need ~1.5e5",
    )


class SensorConfig(StrictModel):
    """The TriDAR hybrid scanner (seed 000 section 4)."""

    fov_deg: tuple[FieldOfView, FieldOfView] = (30.0, 30.0)
    triangulation: TriangulationConfig = TriangulationConfig()
    tof: TOFConfig = TOFConfig()
    transition_range_m: Range | None = Field(
        None, description="triangulation/TOF switch; default: where their noise models cross"
    )
    beam: BeamConfig = BeamConfig()
    pointing: PointingConfig = PointingConfig()
    material: MaterialResponseConfig = MaterialResponseConfig()
    faults: FaultsConfig = FaultsConfig()
    scan: ScanConfig = ScanConfig()

    @model_validator(mode="after")
    def _derive_transition(self) -> SensorConfig:
        if self.transition_range_m is None:
            k, s = self.triangulation.noise_k_per_m, self.tof.noise_sigma_m
            r = math.sqrt(s / k) if k > 0 and s > 0 else 7.0
            # validate_assignment would recurse; set the derived value directly.
            object.__setattr__(self, "transition_range_m", min(r, self.triangulation.max_range_m))
        return self


class FlashLidarConfig(StrictModel):
    """Flash LiDAR of seed 003 section 3.1: a grid of pixels captured at one instant."""

    rows: Annotated[Int, Field(ge=2, le=4096)] = 500
    cols: Annotated[Int, Field(ge=2, le=4096)] = 500
    fov_deg: tuple[FieldOfView, FieldOfView] = (20.0, 20.0)
    range_error_m: Sigma = 0.01
    error_model: Literal["uniform", "gaussian"] = "uniform"
    min_range_m: NonNegRange = 0.5
    max_range_m: Range = 150.0
    grazing_limit_deg: Annotated[Float, Field(gt=0, le=90)] = 85.0


#: Upper bound of the thermal imager's range gate [m]: a passive camera sees far beyond the
#: mission geometry's ``MAX_RANGE_M``.
MAX_THERMAL_RANGE_M = 1e6
Temperature = Annotated[Float, Field(gt=0, le=1000)]  # [K]
Wavelength = Annotated[Float, Field(ge=1, le=30)]  # [um]


class ThermalImagerConfig(StrictModel):
    """Passive thermal infrared imager (seed 000 section 5: the ISS detected at 43.4 km, day and
    night): an uncooled LWIR microbolometer camera and the radiometric model of the target.

    The defaults are a 640 x 480 array over 20 x 15 deg (0.55 mrad pixels) with the NETD, optics
    blur and eclipse temperature of :mod:`perception.sensing.sensors.thermal` (its docstring gives
    the link budget): on ``iss_port`` the detection probability is ~1 out to 45-50 km by night
    from any aspect and falls beyond ~55 km (~90 km by day, the sunlit side being warmer).
    """

    rows: Annotated[Int, Field(ge=2, le=4096)] = 480
    cols: Annotated[Int, Field(ge=2, le=4096)] = 640
    fov_deg: tuple[FieldOfView, FieldOfView] = Field(
        (20.0, 15.0), description="full field of view (horizontal, vertical) [deg]"
    )
    band_um: tuple[Wavelength, Wavelength] = Field(
        (8.0, 14.0), description="spectral band (low, high) [um]; LWIR by default"
    )
    netd_k: Annotated[Float, Field(gt=0, le=10)] = Field(
        0.08, description="noise-equivalent temperature difference per pixel and frame [K]"
    )
    netd_reference_k: Temperature = Field(
        300.0, description="scene temperature at which the NETD is quoted [K]"
    )
    frame_rate_hz: Annotated[Float, Field(gt=0, le=1000)] = Field(
        9.0, description="frames per second (the NETD is quoted at this rate)"
    )
    psf_sigma_px: Annotated[Float, Field(ge=0, le=20)] = Field(
        0.8, description="optics blur: Gaussian point-spread sigma [pixels]"
    )
    supersampling: Annotated[Int, Field(ge=1, le=16)] = Field(
        2, description="minimum sub-rays per pixel and axis"
    )
    min_samples_across_target: Annotated[Int, Field(ge=1, le=256)] = Field(
        24,
        description="sub-rays across the target's bounding diameter, at least (a far target "
        "gets more sub-rays per pixel, so its few pixels' fill fractions are not aliased)",
    )
    max_supersampling: Annotated[Int, Field(ge=1, le=64)] = Field(
        16, description="most sub-rays per pixel and axis"
    )
    detection_threshold_sigma: Annotated[Float, Field(gt=0, le=100)] = Field(
        5.0, description="a pixel is lit above this many noise sigmas"
    )
    min_blob_pixels: Annotated[Int, Field(ge=1, le=10_000)] = Field(
        1, description="lit pixels a connected blob needs to count as a detection"
    )
    centroid_margin_px: Annotated[Int, Field(ge=0, le=50)] = Field(
        2,
        description="the centroid aperture is the blob grown by this many pixels (keeps the "
        "PSF wings, so the centroid is not pulled toward the brightest pixel)",
    )
    max_range_m: Annotated[Float, Field(gt=0, le=MAX_THERMAL_RANGE_M)] = Field(
        200_000.0, description="range gate: nothing is rendered or reported beyond it [m]"
    )
    emissivity: Annotated[Float, Field(ge=0.01, le=1)] = Field(
        0.85, description="LWIR emissivity of every face (beta cloth, white paint: 0.8-0.9)"
    )
    solar_absorptivity: Annotated[Float, Field(ge=0, le=1)] = Field(
        0.3, description="solar absorptivity of every face (beta cloth, white paint: 0.2-0.4)"
    )
    grey_from_reflectivity: StrictBool = Field(
        False,
        description="each face a grey body: absorptivity = emissivity = 1 - its reflectivity "
        "(Kirchhoff, reading the laser albedo as the thermal one) instead of the two constants",
    )
    solar_constant_w_m2: Annotated[Float, Field(ge=0, le=10_000)] = Field(
        1361.0, description="solar irradiance at the target [W/m^2]"
    )
    shade_temperature_k: Temperature = Field(
        240.0, description="faces facing away from the Sun or shadowed, by day [K]"
    )
    eclipse_temperature_k: Temperature = Field(
        230.0, description="every face in the Earth's shadow (night) [K]"
    )
    background_temperature_k: Annotated[Float, Field(ge=0, le=400)] = Field(
        2.7, description="deep-space background behind the target [K]"
    )
    self_shadowing: StrictBool = Field(
        True, description="cast shadow rays: a face the target itself shades from the Sun is cold"
    )

    @model_validator(mode="after")
    def _check(self) -> ThermalImagerConfig:
        lo, hi = self.band_um
        if lo >= hi:
            raise ValueError(f"band_um={self.band_um}: the low edge must be below the high edge")
        if self.supersampling > self.max_supersampling:
            raise ValueError(
                f"supersampling={self.supersampling} must not exceed "
                f"max_supersampling={self.max_supersampling}"
            )
        return self
