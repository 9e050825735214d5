"""The seed-003 line tracker: public API name (DESIGN.md), re-exported from :mod:`perception.estimation.linetrack`."""

from perception.estimation.linetrack import *
from perception.estimation.linetrack import __all__  # noqa: F401
