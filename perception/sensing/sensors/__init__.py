"""Sensors: the TriDAR hybrid scanner (triangulation + TOF), the flash LiDAR of seed 003, faults.

``make_sensor(config)`` returns the sensor a config describes.
"""

from __future__ import annotations

from perception.config import FlashLidarConfig, SensorConfig
from perception.sensing.sensors.faults import FaultInjector
from perception.sensing.sensors.flash import FlashLidar
from perception.sensing.sensors.motion import RelativeMotion, sample_poses
from perception.sensing.sensors.tridar import TriDARSensor

__all__ = [
    "FaultInjector",
    "FlashLidar",
    "RelativeMotion",
    "TriDARSensor",
    "make_sensor",
    "sample_poses",
]


def make_sensor(config: SensorConfig | FlashLidarConfig | None = None) -> TriDARSensor | FlashLidar:
    """A :class:`TriDARSensor` for a ``SensorConfig`` (or None), a :class:`FlashLidar` for a
    ``FlashLidarConfig``."""
    if config is None or isinstance(config, SensorConfig):
        return TriDARSensor(config)
    if isinstance(config, FlashLidarConfig):
        return FlashLidar(config)
    raise ValueError(
        f"config={type(config).__name__}; expected SensorConfig, FlashLidarConfig or None"
    )
