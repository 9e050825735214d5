"""Everything a TriDAR box contains: targets, scan patterns, sensors, estimators, modes, pipeline.

This package never imports ``tridar_env`` or ``agents``: data flows one way (DESIGN.md).
"""

__version__ = "0.1.0"
