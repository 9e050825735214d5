"""The flash LiDAR trackers: public API name, re-exported from
:mod:`perception.estimation.flashtrack`."""

from perception.estimation.flashtrack import *
from perception.estimation.flashtrack import __all__  # noqa: F401
