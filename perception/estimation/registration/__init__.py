"""ICP tracking and the pose covariance of a frame (:mod:`.tracking`), with the exact-face index of
the model (:mod:`.facegrid`)."""

from perception.estimation.registration.tracking import *
from perception.estimation.registration.tracking import __all__, per_point_sigma  # noqa: F401
