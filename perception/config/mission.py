"""A whole scenario: the model of a mission YAML file, one section per concern."""

from __future__ import annotations

from pydantic import Field

from perception.config.dynamics import DynamicsConfig
from perception.config.env import EnvConfig
from perception.config.pipeline import PipelineConfig
from perception.config.sensor import FlashLidarConfig, SensorConfig, ThermalImagerConfig
from perception.config.target import TargetConfig
from perception.config.types import StrictModel


class MissionConfig(StrictModel):
    """A whole scenario: target, sensors (TriDAR, flash LiDAR, thermal imager), estimators,
    dynamics and environment."""

    name: str = Field("mission", max_length=200)
    description: str = Field("", max_length=10_000)
    target: TargetConfig = TargetConfig()
    sensor: SensorConfig = SensorConfig()
    flash: FlashLidarConfig = FlashLidarConfig()
    thermal: ThermalImagerConfig = ThermalImagerConfig()
    pipeline: PipelineConfig = PipelineConfig()
    dynamics: DynamicsConfig = DynamicsConfig()
    env: EnvConfig = EnvConfig()
