"""Configuration: pydantic models, one per concern, read from YAML with a bounded safe loader.

This is the one place where configuration is defined (``perception`` cannot import ``tridar_env``,
so the models of every concern live here and both packages use them). A mission YAML file has the
shape of :class:`MissionConfig`; every section is optional and falls back to documented physical
defaults. Unknown keys and bad values are rejected with a one-line message naming the field, the
value (cut short) and what was expected. Reading is bounded whatever the file holds: size, nesting
and alias expansion have limits, duplicate keys are refused. A number field takes an int or a
float, never a bool or a string, and every physical quantity has an upper bound.

The package: :mod:`~perception.config.types` (number types and bounds, the strict base model),
:mod:`~perception.config.errors` (one-line messages), :mod:`~perception.config.yamlio` (the bounded
YAML reader), one module of models per concern (:mod:`~perception.config.target`,
:mod:`~perception.config.sensor`, :mod:`~perception.config.estimation`,
:mod:`~perception.config.pipeline`, :mod:`~perception.config.dynamics`,
:mod:`~perception.config.env`, :mod:`~perception.config.mission`) and
:mod:`~perception.config.load` (overrides, validation, saving). Import from here.

Example:
    >>> from perception.config import load_config
    >>> cfg = load_config("configs/missions/final_approach.yaml", sensor__tof__noise_sigma_m=0.03)
    >>> cfg.sensor.tof.noise_sigma_m
    0.03
"""

from __future__ import annotations

from perception.config.dynamics import (
    ChaserConfig,
    DynamicsConfig,
    OrbitConfig,
    TargetAttitudeConfig,
)
from perception.config.env import (
    DockingEnvelopeConfig,
    EnvConfig,
    InitialStateConfig,
    RewardConfig,
)
from perception.config.errors import ConfigError, short_repr
from perception.config.estimation import ICPConfig, PAHConfig
from perception.config.load import (
    CONFIG_DIR,
    apply_overrides,
    config_path,
    flatten_overrides,
    load_config,
    resolve_config,
    save_config,
    shipped_configs,
)
from perception.config.mission import MissionConfig
from perception.config.pipeline import (
    CorridorConfig,
    IntegrityConfig,
    PipelineConfig,
    ScanPlanConfig,
)
from perception.config.sensor import (
    BeamConfig,
    FaultsConfig,
    FlashLidarConfig,
    MaterialResponseConfig,
    OccluderConfig,
    PointingConfig,
    ScanConfig,
    SensorConfig,
    ThermalImagerConfig,
    TOFConfig,
    TriangulationConfig,
)
from perception.config.target import TargetConfig
from perception.config.types import StrictModel
from perception.config.yamlio import MAX_FILE_BYTES, MAX_NESTING, MAX_NODES, load_yaml, parse_yaml

__all__ = [
    "CONFIG_DIR",
    "MAX_FILE_BYTES",
    "MAX_NESTING",
    "MAX_NODES",
    "BeamConfig",
    "ChaserConfig",
    "ConfigError",
    "CorridorConfig",
    "DockingEnvelopeConfig",
    "DynamicsConfig",
    "EnvConfig",
    "FaultsConfig",
    "FlashLidarConfig",
    "ICPConfig",
    "InitialStateConfig",
    "IntegrityConfig",
    "MaterialResponseConfig",
    "MissionConfig",
    "OccluderConfig",
    "OrbitConfig",
    "PAHConfig",
    "PipelineConfig",
    "PointingConfig",
    "RewardConfig",
    "ScanConfig",
    "ScanPlanConfig",
    "SensorConfig",
    "StrictModel",
    "TOFConfig",
    "TargetAttitudeConfig",
    "TargetConfig",
    "ThermalImagerConfig",
    "TriangulationConfig",
    "apply_overrides",
    "config_path",
    "flatten_overrides",
    "load_config",
    "load_yaml",
    "parse_yaml",
    "resolve_config",
    "save_config",
    "shipped_configs",
    "short_repr",
]
