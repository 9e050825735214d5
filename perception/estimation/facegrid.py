"""The exact-face voxel index, moved to :mod:`perception.estimation.registration.facegrid`."""

from perception.estimation.registration.facegrid import *
