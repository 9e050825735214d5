"""Scan patterns: public API name (DESIGN.md), re-exported from :mod:`perception.sensing.scan_patterns`."""

from perception.sensing.scan_patterns import *  # noqa: F403
from perception.sensing.scan_patterns import __all__  # noqa: F401
