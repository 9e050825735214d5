"""Configuration of the target: a library name or a mesh file, its scale, port and material."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, model_validator

from perception.config.types import (
    MAX_MASS_KG,
    Float,
    StrictModel,
    UnitFloat,
    Vec3,
)


class TargetConfig(StrictModel):
    """Which target to approach: a library name or a mesh file."""

    name: str = Field(
        "cubesat", max_length=4096,
        description="library name (cubesat, cygnss, iss_port, hubble) or mesh path",
    )
    scale: Annotated[Float, Field(gt=0, le=1000)] = 1.0
    port_position_m: Vec3 | None = None
    port_axis: Vec3 | None = None
    mass_kg: Annotated[Float, Field(ge=0.1, le=MAX_MASS_KG)] | None = None
    reflectivity: UnitFloat = 0.5

    @model_validator(mode="after")
    def _port_pair(self) -> TargetConfig:
        if (self.port_position_m is None) != (self.port_axis is None):
            raise ValueError("port_position_m and port_axis must be given together")
        return self

