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
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from perception.config import FlashLidarConfig, ICPConfig
from perception.geometry import check_rigid
from perception.sensing.pointcloud import PointCloud
from perception.estimation.registration import ModelCloud, RegistrationResult, icp, prepare_model
from perception.targets import TargetModel
from perception.estimation.voxel import adaptive_voxel_size, voxel_downsample

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "SEED_FROM_OURS",
    "T_from_seed_pose",
    "seed_pose_from_T",
    "depth_map",
    "gaussian_downsample",
    "Lines",
    "LineMatches",
    "detect_lines",
    "line_similarity",
    "match_lines",
    "roll_variation",
    "roll_about_boresight",
    "adaptive_voxel_size",
    "voxel_downsample",
    "seed003_icp_config",
    "LineTrackInfo",
    "LineRollTracker",
]

#: ``p_seed = SEED_FROM_OURS @ p_ours``: seed (X, Y, Z) = our (z, x, y). Used for both the sensor
#: and the target frame.
SEED_FROM_OURS: FloatArray = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
SEED_FROM_OURS.setflags(write=False)

#: Seed 003 section 2.7: ICP stops when its mean squared error changes by less than this [m^2].
SEED_ICP_EPS_M2 = 1e-6


# ---------------------------------------------------------------------------------------------
# Seed frames
# ---------------------------------------------------------------------------------------------
def T_from_seed_pose(position_seed: npt.ArrayLike, rpy_seed_rad: npt.ArrayLike) -> FloatArray:
    """``T_sensor_target`` (our axes) from a pose written in seed 003's frames.

    Args:
        position_seed: (3,) target origin in the seed's sensor frame (X toward the target, Y
            right, Z down) [m]; seed 003's (x, y, z) of sections 3.2 / 3.3.
        rpy_seed_rad: (3,) roll, pitch, yaw (phi, theta, psi) [rad] of eq. (2).

    Returns:
        (4, 4) pose mapping target-body coordinates into our sensor frame.
    """
    pos = np.asarray(position_seed, dtype=np.float64).reshape(-1)
    rpy = np.asarray(rpy_seed_rad, dtype=np.float64).reshape(-1)
    if pos.shape != (3,) or not np.all(np.isfinite(pos)):
        raise ValueError(f"position_seed={pos}; expected 3 finite values [m]")
    if rpy.shape != (3,) or not np.all(np.isfinite(rpy)):
        raise ValueError(f"rpy_seed_rad={rpy}; expected 3 finite angles [rad]")
    P = SEED_FROM_OURS
    R_seed = Rotation.from_euler("XYZ", rpy).as_matrix()
    T = np.eye(4)
    T[:3, :3] = P.T @ R_seed @ P
    T[:3, 3] = P.T @ pos
    return T


def seed_pose_from_T(T_sensor_target: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Inverse of :func:`T_from_seed_pose`: (position_seed (3,) [m], rpy (3,) [rad]).

    Roll and yaw are in (-pi, pi], pitch in [-pi/2, pi/2].
    """
    T = check_rigid(T_sensor_target, "T_sensor_target")
    P = SEED_FROM_OURS
    R_seed = P @ T[:3, :3] @ P.T
    return P @ T[:3, 3], Rotation.from_matrix(R_seed).as_euler("XYZ")


# ---------------------------------------------------------------------------------------------
# Depth map (eq. 4) and Gaussian downsampling (eq. 5)
# ---------------------------------------------------------------------------------------------
def _fov_pair(fov_rad: float | tuple[float, float] | npt.ArrayLike) -> tuple[float, float]:
    f = np.asarray(fov_rad, dtype=np.float64).reshape(-1)
    if f.size == 1:
        f = np.repeat(f, 2)
    if f.size != 2 or not np.all(np.isfinite(f)) or np.any(f <= 0) or np.any(f >= math.pi):
        raise ValueError(
            f"fov_rad={fov_rad!r}; expected one or two (horizontal, vertical) angles in (0, pi) [rad]"
        )
    return float(f[0]), float(f[1])


def depth_map(
    points: npt.ArrayLike,
    fov_rad: float | tuple[float, float],
    shape: tuple[int, int],
    *,
    floor_gray: int = 0,
) -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.bool_]]:
    """Grey depth image of a cloud, seed 003 eq. (4) in our axes (depth = z, the boresight).

    ``I(r, c) = floor + (255 - floor) (1 - (z - z_min) / (z_max - z_min))`` with
    ``r = arctan(y / z) / (fov_v / rows) + rows / 2`` and ``c = arctan(x / z) / (fov_h / cols) +
    cols / 2`` (floored to pixel indices). Near is bright; empty pixels are 0. Where several points
    fall on one pixel the nearest wins. With ``floor_gray=0`` this is eq. (4) verbatim.

    Args:
        points: (N, 3) float64 [m], sensor frame (+z boresight, +x right, +y down). Points with
            z <= 0, non-finite or outside the field of view are ignored.
        fov_rad: full field of view [rad], one angle or (horizontal, vertical) as in
            :class:`~perception.config.FlashLidarConfig` ``fov_deg``.
        shape: (rows, cols) of the image.
        floor_gray: grey level 0..254 of the farthest point.

    Returns:
        image (rows, cols) uint8 and valid (rows, cols) bool (pixels that received a point).
    """
    fov_h, fov_v = _fov_pair(fov_rad)
    if len(shape) != 2 or int(shape[0]) < 2 or int(shape[1]) < 2:
        raise ValueError(f"shape={shape!r}; expected (rows, cols) with both >= 2")
    if not 0 <= int(floor_gray) < 255:
        raise ValueError(f"floor_gray={floor_gray}; expected an integer grey level in [0, 254]")
    rows, cols = int(shape[0]), int(shape[1])
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    image = np.zeros((rows, cols), dtype=np.uint8)
    valid = np.zeros((rows, cols), dtype=bool)
    keep = np.all(np.isfinite(p), axis=1) & (p[:, 2] > 0.0)
    p = p[keep]
    if p.shape[0] == 0:
        return image, valid
    z = p[:, 2]
    r = np.floor(np.arctan(p[:, 1] / z) / (fov_v / rows) + rows / 2).astype(np.int64)
    c = np.floor(np.arctan(p[:, 0] / z) / (fov_h / cols) + cols / 2).astype(np.int64)
    inside = (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
    r, c, z = r[inside], c[inside], z[inside]
    if z.size == 0:
        return image, valid
    z_min, z_max = float(z.min()), float(z.max())
    span = z_max - z_min
    frac = (z - z_min) / span if span > 0 else np.zeros_like(z)
    fl = float(floor_gray)
    gray = np.rint(fl + (255.0 - fl) * (1.0 - frac)).astype(np.uint8)
    flat = r * cols + c
    img_flat = image.reshape(-1)
    np.maximum.at(img_flat, flat, gray)
    valid.reshape(-1)[flat] = True
    return image, valid


def gaussian_downsample(image: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    """Seed 003 eq. (5): 5x5 Gaussian blur with sigma 1, then keep every second row and column.

    Args:
        image: (rows, cols) uint8.

    Returns:
        (ceil(rows / 2), ceil(cols / 2)) uint8; pixel (i, j) is the blurred pixel (2 i, 2 j).
    """
    img = np.ascontiguousarray(image, dtype=np.uint8)
    if img.ndim != 2:
        raise ValueError(f"image has shape {img.shape}; expected a (rows, cols) grey image")
    return np.ascontiguousarray(cv2.GaussianBlur(img, (5, 5), 1.0)[::2, ::2])


# ---------------------------------------------------------------------------------------------
# Lines and their descriptors (eqs. 6-7)
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Lines:
    """Line segments of one depth map with their seed-003 descriptors.

    Coordinates are pixels of the full-resolution depth map, x = column, y = row (top-left pixel
    centre at (0, 0)).

    Attributes:
        segments: (L, 4) float64 endpoints (x1, y1, x2, y2) [px], LSD's direction.
        length: (L,) float64 [px].
        gradient: (L,) float64 mean grey-gradient magnitude along the line, eq. (7) [grey/px of the
            downsampled image].
        angle: (L,) float64 directed orientation ``atan2(y2 - y1, x2 - x1)`` in (-pi, pi] [rad].
        midpoint: (L, 2) float64 (x, y) [px].
    """

    segments: FloatArray
    length: FloatArray
    gradient: FloatArray
    angle: FloatArray
    midpoint: FloatArray

    def __len__(self) -> int:
        return int(self.length.shape[0])

    @classmethod
    def empty(cls) -> Lines:
        """No lines (right dtypes and shapes)."""
        z = np.zeros(0)
        return cls(np.zeros((0, 4)), z, z.copy(), z.copy(), np.zeros((0, 2)))

    def longest(self, q: int) -> npt.NDArray[np.intp]:
        """Indices of the ``q`` longest lines, longest first (stable for equal lengths)."""
        return np.argsort(-self.length, kind="stable")[: max(int(q), 0)]

    def subset(self, idx: npt.ArrayLike) -> Lines:
        """The lines at ``idx`` (index array or boolean mask)."""
        i = np.asarray(idx)
        return Lines(self.segments[i], self.length[i], self.gradient[i], self.angle[i],
                     self.midpoint[i])


def _make_detector() -> Any:
    """OpenCV's LSD; the FastLineDetector of opencv-contrib only where this build lacks LSD."""
    if hasattr(cv2, "createLineSegmentDetector"):
        try:
            return cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
        except cv2.error:  # builds 4.1-4.5.0 shipped the symbol without the implementation
            pass
    ximgproc = getattr(cv2, "ximgproc", None)
    if ximgproc is not None and hasattr(ximgproc, "createFastLineDetector"):
        return ximgproc.createFastLineDetector()
    raise RuntimeError(
        f"OpenCV {cv2.__version__} has neither createLineSegmentDetector (LSD) nor "
        "ximgproc.createFastLineDetector; install opencv-python-headless >= 4.5.1"
    )


def _mean_gradient(image: npt.NDArray[np.uint8], segments: FloatArray) -> FloatArray:
    """Eq. (7): mean Sobel gradient magnitude over the pixels along each segment (image coords)."""
    f = image.astype(np.float32)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    mag = np.hypot(gx, gy).astype(np.float64)
    p1, p2 = segments[:, :2], segments[:, 2:]
    n = np.maximum(np.ceil(np.linalg.norm(p2 - p1, axis=1)).astype(np.int64), 1) + 1
    line = np.repeat(np.arange(n.size), n)
    start = np.concatenate([[0], np.cumsum(n)[:-1]])
    s = (np.arange(line.size) - start[line]) / (n[line] - 1)
    xy = p1[line] + s[:, None] * (p2 - p1)[line]
    cx = np.clip(np.rint(xy[:, 0]).astype(np.int64), 0, image.shape[1] - 1)
    cy = np.clip(np.rint(xy[:, 1]).astype(np.int64), 0, image.shape[0] - 1)
    return np.bincount(line, weights=mag[cy, cx], minlength=n.size) / n


def detect_lines(
    image: npt.ArrayLike, *, downsample: bool = True, detector: Any | None = None
) -> Lines:
    """Lines of a depth map: eq. (5) downsampling, then LSD (eq. 6), then the descriptors.

    Args:
        image: (rows, cols) uint8 depth map (:func:`depth_map`).
        downsample: apply :func:`gaussian_downsample` first (seed 003); coordinates are scaled
            back to ``image`` pixels either way.
        detector: a reusable ``cv2.LineSegmentDetector`` (one is created when None).

    Returns:
        :class:`Lines` in the order LSD reports them.
    """
    img = np.ascontiguousarray(image, dtype=np.uint8)
    if img.ndim != 2:
        raise ValueError(f"image has shape {img.shape}; expected a (rows, cols) grey image")
    small = gaussian_downsample(img) if downsample else img
    scale = 2.0 if downsample else 1.0
    det = detector if detector is not None else _make_detector()
    found = det.detect(small)[0]
    if found is None or len(found) == 0:
        return Lines.empty()
    seg = np.asarray(found, dtype=np.float64).reshape(-1, 4)
    grad = _mean_gradient(small, seg)
    seg = seg * scale
    d = seg[:, 2:] - seg[:, :2]
    return Lines(
        segments=seg,
        length=np.hypot(d[:, 0], d[:, 1]),
        gradient=grad,
        angle=np.arctan2(d[:, 1], d[:, 0]),
        midpoint=0.5 * (seg[:, :2] + seg[:, 2:]),
    )


# ---------------------------------------------------------------------------------------------
# Matching (eqs. 8-13) and roll (eqs. 14-15)
# ---------------------------------------------------------------------------------------------
def _ratio(a: FloatArray, b: FloatArray) -> FloatArray:
    """min / max of every pair (a_i, b_j), 1 where both are 0; inputs are >= 0."""
    lo = np.minimum(a[:, None], b[None, :])
    hi = np.maximum(a[:, None], b[None, :])
    return np.where(hi > 0, lo / np.where(hi > 0, hi, 1.0), 1.0)


def line_similarity(prev: Lines, cur: Lines, alpha: float = 0.25) -> FloatArray:
    """Similarity matrix of eq. (13): ``sm[i, j]`` of eq. (12) between ``prev[i]`` and ``cur[j]``.

    ``sm = alpha (sm1 + sm2 + sm3 + sm4)``: length ratio (8), gradient ratio (9), orientation
    ``max(cos(angle_i - angle_j), 0)`` (10) and midpoint coordinate ratios (11). With
    ``alpha = 0.25`` it lies in [0, 1].

    Returns:
        (len(prev), len(cur)) float64.
    """
    if not (math.isfinite(alpha) and alpha > 0):
        raise ValueError(f"alpha={alpha}; expected a finite weight > 0")
    sm1 = _ratio(prev.length, cur.length)
    sm2 = _ratio(prev.gradient, cur.gradient)
    sm3 = np.maximum(np.cos(prev.angle[:, None] - cur.angle[None, :]), 0.0)
    mp = np.maximum(prev.midpoint, 0.0)
    mc = np.maximum(cur.midpoint, 0.0)
    sm4 = 0.5 * (_ratio(mp[:, 0], mc[:, 0]) + _ratio(mp[:, 1], mc[:, 1]))
    return alpha * (sm1 + sm2 + sm3 + sm4)


@dataclass(frozen=True)
class LineMatches:
    """Matched line pairs between two frames.

    Attributes:
        prev: (M,) indices into the previous frame's :class:`Lines`.
        cur: (M,) indices into the current frame's :class:`Lines`.
        score: (M,) similarity of each pair, eq. (12).
    """

    prev: npt.NDArray[np.intp]
    cur: npt.NDArray[np.intp]
    score: FloatArray

    def __len__(self) -> int:
        return int(self.prev.shape[0])


def match_lines(
    prev: Lines, cur: Lines, alpha: float = 0.25, threshold: float = 0.8, q: int = 10
) -> LineMatches:
    """Match the ``q`` longest lines of two frames (seed 003 section 2.5).

    For each of the current frame's selected lines (a column of the similarity matrix) the most
    similar previous line is its match when the similarity exceeds ``threshold``.

    Args:
        prev: lines of frame k-1.
        cur: lines of frame k.
        alpha: weight of each similarity term (eq. 12).
        threshold: ``T_d``, minimum similarity of a match.
        q: number of longest lines taken from each frame (``Q_{k-1}``, ``Q_k``), >= 1.

    Returns:
        :class:`LineMatches` with indices into ``prev`` and ``cur``.
    """
    if int(q) < 1:
        raise ValueError(f"q={q}; expected >= 1 lines per frame")
    if not math.isfinite(threshold):
        raise ValueError(f"threshold={threshold}; expected a finite similarity")
    if len(prev) == 0 or len(cur) == 0:
        empty = np.zeros(0, dtype=np.intp)
        return LineMatches(empty, empty.copy(), np.zeros(0))
    ip = prev.longest(q)
    ic = cur.longest(q)
    sdm = line_similarity(prev.subset(ip), cur.subset(ic), alpha)
    best = np.argmax(sdm, axis=0)
    score = sdm[best, np.arange(ic.size)]
    ok = score > threshold
    return LineMatches(ip[best[ok]], ic[ok], score[ok])


def _wrap(a: FloatArray) -> FloatArray:
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def roll_variation(
    prev: Lines, cur: Lines, matches: LineMatches, *, max_deviation_rad: float | None = None
) -> float | None:
    """Eq. (14): roll of the target about our +z (boresight) from frame k-1 to k [rad].

    The mean of the wrapped orientation changes ``angle_cur - angle_prev`` of the matched lines;
    positive when the target turns from +x toward +y (see the module docstring for the sign).

    Args:
        prev: lines of frame k-1.
        cur: lines of frame k.
        matches: pairs from :func:`match_lines`.
        max_deviation_rad: when given, pairs whose change differs from the median change by more
            than this are left out of the mean (short lines on a face-on target are sometimes
            matched to the wrong partner; the seed averages every pair). None: eq. (14) verbatim.

    Returns:
        The roll variation in (-pi, pi], or None when there is no match.
    """
    if len(matches) == 0:
        return None
    d = _wrap(cur.angle[matches.cur] - prev.angle[matches.prev])
    if max_deviation_rad is not None:
        if not (math.isfinite(max_deviation_rad) and max_deviation_rad > 0):
            raise ValueError(f"max_deviation_rad={max_deviation_rad}; expected an angle > 0 [rad]")
        med = float(np.median(d))
        d = d[np.abs(_wrap(d - med)) <= max_deviation_rad]
    return float(np.mean(d))


def roll_about_boresight(T_sensor_target: npt.ArrayLike, delta_roll: float) -> FloatArray:
    """The roll prior of eqs. (15) and (17): turn the target by ``delta_roll`` [rad] about the
    boresight direction through its own origin (``R <- Rz(delta_roll) R``, position unchanged)."""
    T = check_rigid(T_sensor_target, "T_sensor_target").copy()
    if not math.isfinite(delta_roll):
        raise ValueError(f"delta_roll={delta_roll}; expected a finite angle [rad]")
    c, s = math.cos(delta_roll), math.sin(delta_roll)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T[:3, :3] = Rz @ T[:3, :3]
    return T


# ---------------------------------------------------------------------------------------------
# Tracker
# ---------------------------------------------------------------------------------------------
def seed003_icp_config(range_sigma_m: float = 0.01 / math.sqrt(3.0), **overrides: Any) -> ICPConfig:
    """Point-to-point ICP settings of seed 003 section 2.7: 100 iterations, stop when the mean
    squared error changes by less than 1e-6 m^2.

    :func:`~perception.estimation.registration.icp` measures that change relative to its noise-normalised
    cost, so the absolute threshold becomes ``1e-6 / range_sigma_m**2``.

    Args:
        range_sigma_m: 1-sigma range noise of the sensor [m] (default: uniform +-10 mm).
        **overrides: further :class:`~perception.config.ICPConfig` fields.
    """
    if not (math.isfinite(range_sigma_m) and range_sigma_m > 0):
        raise ValueError(f"range_sigma_m={range_sigma_m}; expected a finite sigma > 0 [m]")
    base: dict[str, Any] = {
        "method": "point_to_point",
        "max_iterations": 100,
        "residual_tol": SEED_ICP_EPS_M2 / range_sigma_m**2,
        # PCL's correspondence distance is unbounded by default; 2 m bridges the seed's 1 m of
        # closing per frame.
        "max_correspondence_m": 2.0,
    }
    base.update(overrides)
    return ICPConfig(**base)


@dataclass(frozen=True)
class LineTrackInfo:
    """What the last :meth:`LineRollTracker.update` (or ``init``) did.

    Attributes:
        delta_roll_rad: roll prior applied (0 when no line matched) [rad].
        roll_from_lines: True when ``delta_roll_rad`` came from matched lines.
        n_lines: lines detected in this frame.
        n_matches: matched line pairs with the previous frame.
        voxel_size_m: grid size ``d_k`` of eq. (16) [m].
        n_points_raw: points in the sensor cloud.
        n_points_used: points after voxel simplification (what ICP saw).
        time_lines_s: depth map + lines + matching [s].
        time_voxel_s: simplification [s].
        time_icp_s: ICP [s].
        time_s: the whole call [s].
    """

    delta_roll_rad: float
    roll_from_lines: bool
    n_lines: int
    n_matches: int
    voxel_size_m: float
    n_points_raw: int
    n_points_used: int
    time_lines_s: float
    time_voxel_s: float
    time_icp_s: float
    time_s: float


class LineRollTracker:
    """Seed-003 tracker: line-based roll prior + adaptive voxel grid + point-to-point ICP.

    Args:
        model: the target (body frame).
        q_lines: ``Q``, longest lines per frame entering the similarity matrix.
        alpha: weight of each similarity term, eq. (12).
        threshold: ``T_d``, minimum similarity of a line match.
        d_model: ``d_m`` of eq. (16), grid size at the initial range [m].
        icp_config: ICP settings; default :func:`seed003_icp_config` for the flash config's noise.
        flash: the flash LiDAR the clouds come from (field of view and pixel grid of the depth
            map); default :class:`~perception.config.FlashLidarConfig`.
        floor_gray: grey level of the farthest point in the depth map (module docstring).
        centroid_prior: also predict the position, by the shift of the cloud's centroid since the
            previous frame (not in the seed, whose eq. (17) leaves the closing motion, 1 m per
            frame in its experiments, to ICP).
        roll_outlier_deg: line pairs whose orientation change is farther than this from the
            median change are left out of eq. (14) (None: every pair, as in the seed).
        model_seed: seed of the model's surface sampling.

    Example:
        >>> import numpy as np
        >>> from perception.geometry import make_T
        >>> from perception.sensing.sensors import FlashLidar
        >>> from perception.targets import load_target
        >>> target, lidar, rng = load_target("cygnss"), FlashLidar(), np.random.default_rng(0)
        >>> T0 = make_T(None, [0.0, 0.0, 30.0])
        >>> tracker = LineRollTracker(target)
        >>> _ = tracker.init(lidar.capture(target, T0, rng), T0)
        >>> res = tracker.update(lidar.capture(target, T0, rng))
        >>> bool(abs(res.T_sensor_target[2, 3] - 30.0) < 0.01)
        True
    """

    def __init__(
        self,
        model: TargetModel,
        *,
        q_lines: int = 10,
        alpha: float = 0.25,
        threshold: float = 0.8,
        d_model: float = 0.03,
        icp_config: ICPConfig | None = None,
        flash: FlashLidarConfig | None = None,
        floor_gray: int = 64,
        centroid_prior: bool = True,
        roll_outlier_deg: float | None = 2.0,
        model_seed: int = 0,
    ) -> None:
        if not isinstance(model, TargetModel):
            raise ValueError(f"model is a {type(model).__name__}; expected a TargetModel")
        if int(q_lines) < 1:
            raise ValueError(f"q_lines={q_lines}; expected >= 1")
        if not (math.isfinite(d_model) and d_model > 0):
            raise ValueError(f"d_model={d_model}; expected a finite grid size > 0 [m]")
        if not (math.isfinite(alpha) and alpha > 0):
            raise ValueError(f"alpha={alpha}; expected a finite weight > 0")
        if not (math.isfinite(threshold)):
            raise ValueError(f"threshold={threshold}; expected a finite similarity")
        self.model = model
        self.flash = flash or FlashLidarConfig()
        sigma = self.flash.range_error_m
        if self.flash.error_model == "uniform":
            sigma /= math.sqrt(3.0)
        self.range_sigma_m = max(sigma, 1e-4)
        self.icp_config = icp_config or seed003_icp_config(self.range_sigma_m)
        self.q_lines = int(q_lines)
        self.alpha = float(alpha)
        self.threshold = float(threshold)
        self.d_model = float(d_model)
        self.floor_gray = int(floor_gray)
        self.centroid_prior = bool(centroid_prior)
        if roll_outlier_deg is not None and not (math.isfinite(roll_outlier_deg) and roll_outlier_deg > 0):
            raise ValueError(f"roll_outlier_deg={roll_outlier_deg}; expected an angle > 0 [deg] or None")
        self.roll_outlier_rad = None if roll_outlier_deg is None else math.radians(roll_outlier_deg)
        self.model_cloud: ModelCloud = prepare_model(
            model, self.icp_config.model_points, seed=model_seed
        )
        self._detector = _make_detector()
        self._fov = tuple(math.radians(v) for v in self.flash.fov_deg)
        self._shape = (self.flash.rows, self.flash.cols)
        self._T: FloatArray | None = None
        self._lines: Lines | None = None
        self._centroid: FloatArray | None = None
        self._x_init = float("nan")
        self.last: LineTrackInfo | None = None

    @property
    def T_sensor_target(self) -> FloatArray | None:
        """The current pose estimate (None before :meth:`init`)."""
        return None if self._T is None else self._T.copy()

    @property
    def x_init(self) -> float:
        """``X_init`` of eq. (16): range along the boresight at initialisation [m]."""
        return self._x_init

    def lines_of(self, points: FloatArray) -> Lines:
        """Depth map (eq. 4) and lines (eqs. 5-7) of one cloud's points."""
        image, _ = depth_map(points, self._fov, self._shape, floor_gray=self.floor_gray)
        return detect_lines(image, detector=self._detector)

    def _register(self, points: FloatArray, T_pred: FloatArray, voxel: float
                  ) -> tuple[RegistrationResult, int, float, float]:
        t0 = time.perf_counter()
        sparse = voxel_downsample(points, voxel)
        t1 = time.perf_counter()
        res = icp(sparse, self.model_cloud, T_pred, sigma=self.range_sigma_m,
                  config=self.icp_config)
        return res, int(sparse.shape[0]), t1 - t0, time.perf_counter() - t1

    def _failed(self, res: RegistrationResult) -> bool:
        # Too few points or correspondences; a run that hit max_iterations still has a pose.
        return not res.converged and res.n_inliers < max(self.icp_config.min_points, 6)

    def init(self, points_or_cloud: PointCloud | npt.ArrayLike, T_sensor_target: npt.ArrayLike
             ) -> RegistrationResult:
        """Start tracking on the first frame from an initial pose (acquisition or truth + error).

        The frame's lines are stored for the next match and ICP refines ``T_sensor_target`` on the
        cloud simplified with ``d_model``; ``X_init`` is the refined range along the boresight.

        Args:
            points_or_cloud: the first frame, a :class:`PointCloud` or (N, 3) points [m], sensor
                frame.
            T_sensor_target: (4, 4) initial pose.

        Returns:
            The ICP result on the first frame (its pose becomes the tracker's state when ICP
            succeeded, otherwise the given pose is kept).
        """
        t0 = time.perf_counter()
        T0 = check_rigid(T_sensor_target, "T_sensor_target")
        if not T0[2, 3] > 0:
            raise ValueError(
                f"T_sensor_target has z = {T0[2, 3]} m; expected the target in front of the sensor"
            )
        points = _points_of(points_or_cloud)
        self._lines = self.lines_of(points)
        self._centroid = _centroid(points)
        t_lines = time.perf_counter() - t0
        res, n_used, t_vox, t_icp = self._register(points, T0, self.d_model)
        self._T = T0.copy() if self._failed(res) else res.T_sensor_target.copy()
        self._x_init = float(self._T[2, 3]) if self._T[2, 3] > 0 else float(T0[2, 3])
        total = time.perf_counter() - t0
        self.last = LineTrackInfo(0.0, False, len(self._lines), 0, self.d_model, points.shape[0],
                                  n_used, t_lines, t_vox, t_icp, total)
        return dataclasses.replace(res, time_s=total)

    def update(self, cloud: PointCloud | npt.ArrayLike) -> RegistrationResult:
        """Track one frame (seed 003 Algorithm 1).

        Args:
            cloud: the current frame, a :class:`PointCloud` or (N, 3) points [m], sensor frame.

        Returns:
            The ICP result from the roll-predicted pose; ``time_s`` covers the whole step. On an
            ICP failure the tracker keeps the predicted pose.
        """
        if self._T is None or self._lines is None:
            raise RuntimeError("LineRollTracker.update called before init(points, T_sensor_target)")
        t0 = time.perf_counter()
        points = _points_of(cloud)
        lines = self.lines_of(points)
        matches = match_lines(self._lines, lines, self.alpha, self.threshold, self.q_lines)
        droll = roll_variation(self._lines, lines, matches,
                               max_deviation_rad=self.roll_outlier_rad)
        T_pred = roll_about_boresight(self._T, droll if droll is not None else 0.0)
        centroid = _centroid(points)
        if self.centroid_prior and self._centroid is not None and centroid is not None:
            T_pred[:3, 3] += centroid - self._centroid
        self._lines = lines
        self._centroid = centroid
        t_lines = time.perf_counter() - t0
        x_prev = float(self._T[2, 3]) if self._T[2, 3] > 0 else self._x_init
        voxel = adaptive_voxel_size(self.d_model, self._x_init, x_prev)
        res, n_used, t_vox, t_icp = self._register(points, T_pred, voxel)
        self._T = T_pred if self._failed(res) else res.T_sensor_target.copy()
        total = time.perf_counter() - t0
        self.last = LineTrackInfo(
            0.0 if droll is None else droll, droll is not None, len(lines), len(matches), voxel,
            points.shape[0], n_used, t_lines, t_vox, t_icp, total,
        )
        return dataclasses.replace(res, time_s=total)


def _centroid(points: FloatArray) -> FloatArray | None:
    return points.mean(axis=0) if points.shape[0] else None


def _points_of(points_or_cloud: PointCloud | npt.ArrayLike) -> FloatArray:
    if isinstance(points_or_cloud, PointCloud):
        return points_or_cloud.points
    p = np.asarray(points_or_cloud, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points have shape {p.shape}; expected (N, 3) [m] or a PointCloud")
    return p[np.all(np.isfinite(p), axis=1)]
