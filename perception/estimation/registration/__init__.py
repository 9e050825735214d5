"""ICP tracking (seed 000 section 3.2) and the pose covariance / Cramer-Rao bound of a frame.

The model side is prepared once per target (:func:`prepare_model`): dense area-uniform surface
samples with their face normals, a KD-tree and the exact faces' :class:`FaceGrid`, cached on the
:class:`~perception.targets.TargetModel` so every frame reuses them. :func:`icp` then aligns a
sparse scan (sensor frame) to that model from an initial ``T_sensor_target`` with Gauss-Newton
point-to-plane steps on SE(3) (default) or closed-form point-to-point (Kabsch) steps (the seed-003
baseline), and returns a :class:`RegistrationResult` whose covariance is the frame's Cramer-Rao
bound.

The modules, in the order the data flows through them:

- :mod:`.facegrid`: the exact-face voxel index of a mesh (:class:`FaceGrid`);
- :mod:`.model`: :class:`ModelCloud` and :func:`prepare_model`;
- :mod:`.scan`: checking the scan's points, range sigmas and ray directions;
- :mod:`.correspondence`: nearest faces, matching along rays, edge ambiguity;
- :mod:`.weights`: the correspondence gate, trimming, noise variance and robust kernels;
- :mod:`.step`: one Gauss-Newton (or Kabsch) step;
- :mod:`.stopping`: the coarse-to-fine hand-over and the stop rule;
- :mod:`.covariance`: information matrix, covariance, degenerate axes;
- :mod:`.final`: the final pass at the returned pose;
- :mod:`.tracking`: :func:`icp`, the loop over the phases;
- :mod:`.result`: :class:`RegistrationResult`, :data:`AXIS_NAMES`, :data:`FAILURE_VARIANCE`.
"""

from perception.estimation.registration.correspondence import edge_ambiguous
from perception.estimation.registration.covariance import (
    covariance_about_sensor_origin,
    covariance_from_information,
    information_matrix,
    information_rows,
)
from perception.estimation.registration.facegrid import FaceGrid
from perception.estimation.registration.model import ModelCloud, prepare_model
from perception.estimation.registration.result import (
    AXIS_NAMES,
    FAILURE_VARIANCE,
    RegistrationResult,
)

# per_point_sigma: not public API, imported by PAH acquisition.
from perception.estimation.registration.scan import per_point_sigma, validate_points  # noqa: F401
from perception.estimation.registration.tracking import icp

__all__ = [
    "AXIS_NAMES",
    "FAILURE_VARIANCE",
    "FaceGrid",
    "ModelCloud",
    "RegistrationResult",
    "covariance_about_sensor_origin",
    "covariance_from_information",
    "edge_ambiguous",
    "icp",
    "information_matrix",
    "information_rows",
    "prepare_model",
    "validate_points",
]
