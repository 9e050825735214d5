"""ICP: public API name (DESIGN.md), re-exported from :mod:`perception.estimation.registration`."""

from perception.estimation.registration import *
from perception.estimation.registration import __all__  # noqa: F401
