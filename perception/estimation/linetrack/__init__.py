"""Seed-003 pose tracker: depth map, LSD lines, roll prior, adaptive voxel grid, point-to-point ICP.

Zhao, Xu and Bo (Sensors 2018) track a tumbling target with a flash LiDAR. Per frame k:

1. the cloud becomes a grey depth map (eq. 4), blurred and halved (eq. 5, 5x5 Gaussian, sigma 1,
   factor 2), and OpenCV's Line Segment Detector finds its lines (eq. 6);
2. each line gets a descriptor (length, mean gradient magnitude (eq. 7), orientation, midpoint);
   the Q longest lines of frames k-1 and k are compared with the weighted similarity of
   eqs. (8)-(12), and a column maximum above the threshold is a match (eq. 13);
3. the mean orientation change of the matched lines is the roll variation (eq. 14), a rotation
   about the boresight (eq. 15) that predicts the new attitude;
4. the cloud is simplified on a voxel grid whose size grows as the range shrinks (eq. 16,
   :mod:`perception.estimation.voxel`), and point-to-point ICP from the prediction gives the pose (eq. 17).

Frames: seed 003 versus ours
----------------------------
The seed's sensor frame has X toward the target (boresight), Z toward the Earth (down) and Y
completing the right-handed triad (so Y points right when looking along X with Z down). Ours has
+z boresight, +x right, +y down. Hence

    seed (X, Y, Z) = our (z, x, y),        p_seed = SEED_FROM_OURS @ p_ours,

a cyclic permutation (det +1), so roll about the seed's X is a rotation about our +z (boresight),
pitch about the seed's Y is about our +x and yaw about the seed's Z is about our +y. We use the same
permutation for the target frame, so at zero roll/pitch/yaw the target axes are parallel to the
sensor axes (seed section 2.1): the CYGNSS-like target's thin axis (body z, 0.47 m) is along the
boresight and its wings (body x) run across the image, left to right.

Seed 003's relative attitude is the roll-pitch-yaw sequence of its eq. (2), which is
``(Rx(phi) Ry(theta) Rz(psi))^T`` (sensor-to-target); the target's attitude in the sensor frame is
therefore ``R_sensor_target = Rx(phi) Ry(theta) Rz(psi)`` in seed axes, intrinsic X-Y'-Z''
(scipy ``"XYZ"``). :func:`T_from_seed_pose` and :func:`seed_pose_from_T` convert.

In the depth map (our axes) column ``c`` grows with x and row ``r`` with y, so the image angle
``atan2(d row, d col)`` of a line grows by exactly ``phi`` when the target rolls by ``+phi`` about
our +z. :func:`roll_variation` returns that angle, ``mean(angle_k - angle_{k-1})``; seed eq. (14)
writes the difference the other way round because its H maps sensor points into the model.

Eq. (17) ``H_k = H_icp H_roll H_{k-1}`` is written for ``H = T_target_sensor``. Here the roll prior
rotates the previous attitude about the boresight direction through the target's origin
(``R_pred = Rz(dphi) R_{k-1}``, ``t_pred = t_{k-1}``: the target spins about its own centre), and
ICP from that prediction returns ``T_sensor_target`` directly, which is ``(H_icp H_roll H_{k-1})^-1``.

Deviations from the letter of the seed, on purpose:

- eq. (4) maps the farthest point to grey 0, the same as the empty background, so a flat part at
  the back of the target (the CYGNSS wings seen face-on) vanishes from the depth map. ``depth_map``
  keeps eq. (4) exactly with ``floor_gray=0``; the tracker uses ``floor_gray=64`` (target depths
  span 64..255, background 0) so that the silhouette is always an edge.
- eq. (14) averages every matched pair; a short line now and then matches the wrong partner
  (5-40 deg off on the face-on CYGNSS), so the tracker first drops pairs farther than
  ``roll_outlier_deg`` (2 deg) from the median change (``roll_variation(max_deviation_rad=None)``
  is eq. (14) verbatim).
- the seed's eq. (17) predicts no translation, leaving its 1 m of closing per frame to ICP; the
  tracker also shifts the predicted position by the change of the cloud's centroid
  (``centroid_prior``), which keeps ICP's first correspondences close.
- LSD returns directed segments (the brighter, nearer side on a fixed side), so orientations are
  in (-pi, pi] and eq. (10) ``cos(dphi)`` is clipped at 0: a line and its opposite-polarity twin do
  not match.

The package: :mod:`~perception.estimation.linetrack.frames` (seed frames, the roll prior as a
pose change), :mod:`~perception.estimation.linetrack.lines` (depth map, lines, matching, roll
variation) and :mod:`~perception.estimation.linetrack.tracker` (:class:`LineRollTracker`).
Import from here.
"""

from __future__ import annotations

from perception.estimation.linetrack.frames import (
    SEED_FROM_OURS,
    T_from_seed_pose,
    roll_about_boresight,
    seed_pose_from_T,
)
from perception.estimation.linetrack.lines import (
    LineMatches,
    Lines,
    depth_map,
    detect_lines,
    gaussian_downsample,
    line_similarity,
    match_lines,
    roll_variation,
)
from perception.estimation.linetrack.tracker import (
    LineRollTracker,
    LineTrackInfo,
    seed003_icp_config,
)
from perception.estimation.voxel import adaptive_voxel_size, voxel_downsample

__all__ = [
    "SEED_FROM_OURS",
    "LineMatches",
    "LineRollTracker",
    "LineTrackInfo",
    "Lines",
    "T_from_seed_pose",
    "adaptive_voxel_size",
    "depth_map",
    "detect_lines",
    "gaussian_downsample",
    "line_similarity",
    "match_lines",
    "roll_about_boresight",
    "roll_variation",
    "seed003_icp_config",
    "seed_pose_from_T",
    "voxel_downsample",
]
