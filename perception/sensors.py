"""The sensors: public API name (DESIGN.md), re-exported from :mod:`perception.sensing.sensors`."""

from perception.sensing.sensors import *
from perception.sensing.sensors import __all__  # noqa: F401
