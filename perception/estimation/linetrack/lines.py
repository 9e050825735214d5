"""The image side of the seed-003 tracker: the depth map (eq. 4), Gaussian downsampling (eq. 5),
line segments and their descriptors (eqs. 6-7), line matching (eqs. 8-13) and the roll
variation of the matched lines (eq. 14)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


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
    positive when the target turns from +x toward +y (see :mod:`perception.estimation.linetrack`
    for the sign).

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
