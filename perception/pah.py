"""PAH acquisition: public API name (DESIGN.md), re-exported from :mod:`perception.estimation.pah`."""

from perception.estimation.pah import *  # noqa: F403
from perception.estimation.pah import __all__  # noqa: F401
