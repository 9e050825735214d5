"""Sensors: the TriDAR hybrid scanner (triangulation + TOF), the flash LiDAR of seed 003, the
passive thermal imager (seed 000's long-range bearing), faults.

``make_sensor(config)`` returns the sensor a config describes.
"""

from __future__ import annotations

from perception.config import FlashLidarConfig, SensorConfig, ThermalImagerConfig
from perception.sensing.sensors.faults import FaultInjector
from perception.sensing.sensors.flash import FlashLidar
from perception.sensing.sensors.motion import RelativeMotion, sample_poses
from perception.sensing.sensors.thermal import ThermalDetection, ThermalFrame, ThermalImager
from perception.sensing.sensors.tridar import TriDARSensor

__all__ = [
    "FaultInjector",
    "FlashLidar",
    "RelativeMotion",
    "ThermalDetection",
    "ThermalFrame",
    "ThermalImager",
    "TriDARSensor",
    "make_sensor",
    "sample_poses",
]


def make_sensor(
    config: SensorConfig | FlashLidarConfig | ThermalImagerConfig | None = None,
) -> TriDARSensor | FlashLidar | ThermalImager:
    """A :class:`TriDARSensor` for a ``SensorConfig`` (or None), a :class:`FlashLidar` for a
    ``FlashLidarConfig``, a :class:`ThermalImager` for a ``ThermalImagerConfig``."""
    if config is None or isinstance(config, SensorConfig):
        return TriDARSensor(config)
    if isinstance(config, FlashLidarConfig):
        return FlashLidar(config)
    if isinstance(config, ThermalImagerConfig):
        return ThermalImager(config)
    raise ValueError(
        f"config={type(config).__name__}; expected SensorConfig, FlashLidarConfig, "
        "ThermalImagerConfig or None"
    )
