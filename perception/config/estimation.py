"""Configuration of the estimators: ICP tracking and polygonal aspect hashing (PAH) acquisition."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, StrictBool

from perception.config.types import (
    MAX_COUNT,
    Float,
    Int,
    NonNegFloat,
    PositiveFloat,
    Size,
    SmallAngle,
    StrictModel,
    UnitFloat,
)


class ICPConfig(StrictModel):
    """ICP tracking settings (seed 000 section 3.2)."""

    method: Literal["point_to_plane", "point_to_point"] = "point_to_plane"
    model_points: Annotated[Int, Field(ge=100, le=2_000_000)] = 20_000
    max_iterations: Annotated[Int, Field(ge=1, le=10_000)] = 50
    max_correspondence_m: Size = Field(0.5, description="initial gating distance")
    min_correspondence_m: Size = Field(0.02, description="floor of the adaptive gate")
    trim_fraction: Annotated[Float, Field(ge=0, lt=1)] = 0.1
    gate_median_factor: NonNegFloat = Field(
        6.0, description="each iteration, drop matches farther than this many times the median "
        "match distance (never below the gate floor; 0: off): stray returns in front of or behind "
        "the surface (1 % of a frame) are rejected however close the pose already is"
    )
    robust_kernel: Literal["none", "huber", "tukey", "cauchy"] = "huber"
    translation_tol_m: Size = 1e-5
    rotation_tol_rad: SmallAngle = 1e-6
    residual_tol: NonNegFloat = 1e-7
    step_tol_sigma: NonNegFloat = Field(
        0.05,
        description="fine phase: converged once a step is below this many sigmas of the frame's "
        "own information (Mahalanobis length; 0 disables)",
    )
    time_budget_s: Annotated[Float, Field(gt=0, le=3600)] | None = None
    min_points: Annotated[Int, Field(ge=6, le=MAX_COUNT)] = 10
    kernel_scale: PositiveFloat = Field(
        2.5, description="robust kernel threshold in units of the residual's noise sigma"
    )
    noise_floor_fraction: NonNegFloat = Field(
        0.2, description="residual noise floor as a fraction of the range sigma (grazing rays)"
    )
    degeneracy_ratio: Annotated[Float, Field(gt=0, lt=1)] = Field(
        1e-4, description="information eigenvalue ratio below which a direction is unobservable"
    )
    min_direction_support: NonNegFloat = Field(
        0.0, description="effective number of points that must carry a direction's information "
        "for it to count as observed (0: off)"
    )
    edge_ambiguity_sigmas: NonNegFloat = Field(
        2.5, description="a grazing match lying within this many range sigmas (plus the model "
        "spacing) of a differently oriented face informs no direction: edge mixing, which held "
        "a flat face's wrong in-plane pose with confidence; the pipeline's outline refinement "
        "then observes those axes from the scan's outline (0: off)"
    )
    model_noise_fraction: NonNegFloat = Field(
        0.1, description="model resolution error as a fraction of the model sample spacing"
    )
    plane_candidates: Annotated[Int, Field(ge=1, le=16)] = Field(
        3, description="fine phase: nearest samples among which the best-fitting plane is matched"
    )
    back_facing_cos: Annotated[Float, Field(ge=-1, le=1)] = Field(
        0.3, description="drop matches whose model normal . ray direction exceeds this (back faces)"
    )
    match_along_rays: StrictBool = Field(
        False, description="match each point to the face its measured ray crosses (unbiased near "
        "edges; PAH turns it on). Every shipped mission turns it on in tracking: closest-face "
        "matching put face-on points near an edge onto back-facing side faces and claimed "
        "in-plane information the scan does not carry (a generated assembly held 5-6 cm off at "
        "8-11 m under a 3 mm sigma; V-bar replay port error under 10 m p95 7.2 mm closest-face, 3.9 mm "
        "along the rays)"
    )


class PAHConfig(StrictModel):
    """Polygonal aspect hashing acquisition (seed 000 section 3.1)."""

    model_points: Annotated[Int, Field(ge=20, le=1_000_000)] = 400
    length_bin_m: Size = 0.05
    length_tolerance_m: Size = 0.05
    polygon_size: Annotated[Int, Field(ge=4, le=6)] = 4
    max_polygons: Annotated[Int, Field(ge=1, le=10_000)] = 40
    max_candidates: Annotated[Int, Field(ge=1, le=MAX_COUNT)] = 20_000
    fit_inlier_m: Size = 0.05
    precheck_points: Annotated[Int, Field(ge=10, le=100_000)] = 60
    accept_fitness: UnitFloat = Field(
        0.98, description="stop once a hypothesis has this fraction of the scan within 3 sigma"
    )

