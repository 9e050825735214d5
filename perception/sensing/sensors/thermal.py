"""Passive thermal infrared imager: seed 000's long-range bearing sensor (the ISS detected at
43.4 km, by day and by night), rendered with Embree at the target's footprint only.

Long module: one sensor whose rendering, detection and predictions share the window, the
radiometry and the noise model; the docstring holds the model and its numbers.

Camera. A ``rows x cols`` uncooled microbolometer over ``fov_deg`` with the pixel geometry of
:class:`~perception.sensing.sensors.flash.FlashLidar`: pixel ``(r, c)`` looks at
``az = ((c + 0.5) / cols - 0.5) * fov_h`` (toward +x) and, downward (+y),
``((r + 0.5) / rows - 0.5) * fov_v``; row 0 is the top. A frame holds in-band radiance
``L`` [W m^-2 sr^-1]; its noise is white, Gaussian, with sigma the noise-equivalent radiance
``NER = NETD * dL/dT(T_ref)`` (the NETD quoted at the reference scene temperature ``T_ref``).

Target radiometry. Each face is a diffuse grey emitter of emissivity ``eps`` (one constant, or
``1 - reflectivity`` with ``grey_from_reflectivity``) at a temperature set by a thin-plate
radiative balance, insulated behind (MLI):
``eps sigma_SB T^4 = eps sigma_SB T_shade^4 + alpha S mu``, ``mu`` the cosine of the Sun's
incidence on the face side the sensor sees (0 when it faces away or, with ``self_shadowing``, when
a shadow ray from the hit point meets the target). Faces away from the Sun sit at
``shade_temperature_k`` by day; at night (``sun_direction_target=None``) every face sits at
``eclipse_temperature_k``. A ray that misses sees the deep-space background
(``background_temperature_k``, ~3 K: nothing in the LWIR); a face adds ``(1 - eps)`` times that
background by reflection. Reflected sunlight in the LWIR (~1.5 W/m^2 of the solar constant in
8-14 um, <1 % of the emission) and the Earth's infrared are left out.
``L_band(T) = int_band 2 h c^2 / lambda^5 / (exp(h c / (lambda k T)) - 1) d lambda`` is tabulated
once per band (0-2,000 K, 0.25 K steps, linear interpolation).

Rendering. Only the pixels covering the projection of the target's bounding sphere
(``target.radius`` about the origin of ``T_sensor_target``) are ray cast, ``n x n`` sub-rays per
pixel on a regular grid; ``n`` grows with range so that at least ``min_samples_across_target``
sub-rays span the target's diameter (a 44 m target at 40 km spans two 0.55 mrad pixels: a coarse
grid would alias its fill fraction and bias the centroid). The sub-rays are point samples of
the scene; the optics blur them with the Gaussian PSF and the pixels integrate the result, which
per axis is a weight ``(1/n) (Phi((i + 1 - x_j)/s) - Phi((i - x_j)/s))`` of sample ``j`` in pixel
``i`` (two sparse matrix products; the window grows by the PSF's reach, 4 sigma). Blurring pixel
values instead keeps the pixel-phase bias of the centroid of a sharp image (~0.07 pixel on a
1.4-pixel cube); what the sub-ray grid leaves is ~0.01 pixel. Noise is added last. On
``iss_port`` a frame at 40 km casts 3,600 rays (5 x 5 pixels, 12 x 12 sub-rays each) into a
13 x 13 window, at 1 km ~30,000 into 94 x 95; by day the sunlit hits add a shadow ray each. The
noise-free window of the last pose is memoised, so predictions and repeated captures at one pose
render once. Only the window is searched: false alarms elsewhere in the frame are not drawn,
which is why ``k`` is 5 (a whole 640 x 480 frame would hold ~0.09 noise pixels above 5 sigma).

Detection. Pixels more than ``k = detection_threshold_sigma`` noise sigmas above the background
are lit; connected lit pixels (8-connectivity, ``scipy.ndimage.label``) form blobs; the blob with
the largest summed signal among those of at least ``min_blob_pixels`` is the target. Its centroid
is the background-subtracted, signal-weighted mean pixel position over an aperture ``A``: the blob
grown by ``centroid_margin_px`` (so the faint PSF wings count and the centroid is not pulled toward
the brightest pixel). The estimator is linear in the pixel values, so its error per axis is
``sigma_x = NER * sqrt(sum_A (x_i - x_c)^2) / S`` pixels, ``S = sum_A (L_i - L_bg)`` the
aperture's signal: the centroid's Cramer-Rao-like bound for white pixel noise, i.e.
``sigma_x ~ sqrt(N_A) * rms_radius / SNR_total``. Times the IFOV (with the small Jacobian from the
pixel's elevation to the bearing's) it is ``ThermalDetection.sigma_rad`` (RMS of the two axes),
computed from the measured ``S``. :meth:`ThermalImager.predicted_bearing_sigma_rad` evaluates it
on the noise-free frame over the aperture expected under the noise (each pixel weighted by the
probability that a lit pixel lies within the margin of it: noise lights pixels the noise-free
blob does not, and the aperture grows with them; with the noise-free blob alone the prediction
came out ~10 % low at a peak SNR of 11). The bearing is
``[az, el] = [atan2(x, z), atan2(-y, hypot(x, z))]`` as in :mod:`perception.pipeline.bearing`;
it points at the target's radiance centroid, which by day
leans toward the sunlit side (by at most the target's apparent radius).

Detection probability. With independent pixel noise a pixel of noise-free signal ``s_i`` is lit
with ``p_i = Phi(s_i / NER - k)``; the probability that at least ``min_blob_pixels`` pixels of the
window are lit is the tail of their Poisson-binomial law: exact for one pixel, an upper bound for
more (lit pixels need not touch). It falls with range as the fill fraction falls (~1/r^2 once the
target is smaller than a pixel) and with the target's apparent size and temperature.

Defaults and seed 000. 640 x 480 over 20 x 15 deg (0.545 mrad), 8-14 um, NETD 80 mK at 300 K
(50 mK is an uncooled array's figure behind an f/1 lens; a compact space lens near f/1.3 costs
~1.7x), 9 Hz, PSF sigma 0.8 px (diffraction at f/1.3 plus pixel crosstalk and jitter), emissivity
0.85 and solar absorptivity 0.3 (beta cloth, white paint), eclipse 230 K and shade 240 K (the MLI
of a crewed station, warmed from within), so a face under a normal Sun sits at 330 K and radiates
5.9 times the eclipse radiance in band (the peak pixel of the oblique ``iss_port`` holds ~10 NER
at 40 km by night, ~32 by day). Averaged over the target's sub-pixel position, the
detection probability on ``iss_port`` (44 m):

=======================  =====  =====  =====  =====  =====  =====  =====  =====
range [km]                  45     50     60     70     80    100    120    150
=======================  =====  =====  =====  =====  =====  =====  =====  =====
night, oblique              1.00   0.99   0.50   0.12   0.02   0.00   0.00   0.00
night, end-on (port)        1.00   1.00   0.83   0.28   0.10   0.04   0.00   0.00
night, broadside            1.00   1.00   1.00   0.66   0.39   0.04   0.00   0.00
Sun 90 deg off, oblique     1.00   1.00   1.00   0.99   0.77   0.11   0.01   0.00
Sun behind, oblique         1.00   1.00   1.00   1.00   1.00   0.73   0.17   0.01
=======================  =====  =====  =====  =====  =====  =====  =====  =====

So the 43.4 km of STS-128 is inside the imager's range by day and by night from any aspect, as
flown, and the detection fades beyond ~55 km by night (~90 km by day) instead of reaching hundreds
of km as a 50 mK camera on a warmer target would. The oblique aspect is the target rotated by
Euler xyz (15, -20, 30) deg; "end-on" looks down the docking port's axis; "Sun behind" is 45 deg
off the line of sight on the sensor's side, "90 deg off" lights the target from the side.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import ndimage, sparse
from scipy.special import ndtr

from perception.config import ThermalImagerConfig
from perception.geometry import check_rigid
from perception.sensing.sensors.raycast import face_planes
from perception.targets import TargetModel

FloatArray = npt.NDArray[np.float64]

__all__ = ["ThermalDetection", "ThermalFrame", "ThermalImager", "band_radiance"]

H_PLANCK = 6.62607015e-34  # [J s]
C_LIGHT = 299_792_458.0  # [m/s]
K_BOLTZMANN = 1.380649e-23  # [J/K]
SIGMA_SB = 5.670374419e-8  # Stefan-Boltzmann [W m^-2 K^-4]

#: Temperature table of the band radiance [K]: 0 to 2,000 K in 0.25 K steps.
_T_STEP = 0.25
_T_MAX = 2000.0
#: Wavelength samples across the band (Simpson's rule).
_N_LAMBDA = 257
#: PSF reach [sigma]: the window grows by this many PSF sigmas around the rendered pixels.
_PSF_TRUNCATE = 4.0
#: Rim samples of the bounding cone (its projection's box gets a pixel of padding for the polygon).
_CONE_SAMPLES = 64
_RIM_COS = np.cos(np.linspace(0.0, 2.0 * math.pi, _CONE_SAMPLES, endpoint=False))[:, None]
_RIM_SIN = np.sin(np.linspace(0.0, 2.0 * math.pi, _CONE_SAMPLES, endpoint=False))[:, None]


# -- radiometry ------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=8)
def _band_table(band_um: tuple[float, float]) -> tuple[FloatArray, FloatArray]:
    """Band radiance ``L`` [W m^-2 sr^-1] and ``dL/dT`` [W m^-2 sr^-1 K^-1] on the temperature
    grid ``0, 0.25, ..., 2000 K`` (read-only)."""
    lam = np.linspace(band_um[0], band_um[1], _N_LAMBDA) * 1e-6
    w = np.full(_N_LAMBDA, 2.0)
    w[1::2] = 4.0
    w[0] = w[-1] = 1.0
    w *= (lam[1] - lam[0]) / 3.0  # Simpson weights
    temps = np.arange(0.0, _T_MAX + _T_STEP / 2, _T_STEP)
    t = temps[1:, None]  # 0 K radiates nothing: row 0 stays 0
    with np.errstate(over="ignore"):
        x = (H_PLANCK * C_LIGHT / K_BOLTZMANN) / (lam[None, :] * t)  # (T, lambda)
        inv_em1 = 1.0 / np.expm1(x)  # 0 where exp(x) overflows (cold)
    spectral = (2.0 * H_PLANCK * C_LIGHT**2 / lam**5)[None, :] * inv_em1
    # dB/dT = B * x e^x / (e^x - 1) / T = B * x * (1 + 1 / (e^x - 1)) / T.
    d_spectral = spectral * x * (1.0 + inv_em1) / t
    L = np.zeros(temps.size)
    dL = np.zeros(temps.size)
    L[1:] = spectral @ w
    dL[1:] = d_spectral @ w
    L.setflags(write=False)
    dL.setflags(write=False)
    return L, dL


def band_radiance(
    temperature_k: npt.ArrayLike, band_um: tuple[float, float] = (8.0, 14.0)
) -> FloatArray:
    """In-band blackbody radiance [W m^-2 sr^-1] of temperatures [K] (clipped to 0-2,000 K).

    Example:
        >>> round(float(band_radiance(300.0)), 1)
        54.9
    """
    L, _ = _band_table((float(band_um[0]), float(band_um[1])))
    temps = np.clip(np.asarray(temperature_k, dtype=np.float64), 0.0, _T_MAX)
    return np.asarray(np.interp(temps / _T_STEP, np.arange(L.size), L), dtype=np.float64)


def _band_radiance_derivative(temperature_k: float, band_um: tuple[float, float]) -> float:
    _, dL = _band_table((float(band_um[0]), float(band_um[1])))
    return float(np.interp(min(max(temperature_k, 0.0), _T_MAX) / _T_STEP, np.arange(dL.size), dL))


# -- results ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ThermalDetection:
    """The target found in one thermal frame.

    Attributes:
        t: frame time [s].
        direction: (3,) unit vector toward the radiance centroid, sensor frame.
        bearing: (2,) ``[az, el]`` [rad]: ``atan2(x, z)``, ``atan2(-y, hypot(x, z))``.
        sigma_rad: 1-sigma bearing error per axis the detector claims [rad] (from the aperture's
            measured SNR and the IFOV; see the module docstring).
        snr: peak pixel signal over the noise sigma.
        n_pixels: lit pixels of the blob.
    """

    t: float
    direction: FloatArray
    bearing: FloatArray
    sigma_rad: float
    snr: float
    n_pixels: int


@dataclass(frozen=True)
class ThermalFrame:
    """The rendered window of one thermal frame (pixels outside it hold only background and noise,
    which nothing downstream reads, so they are not drawn).

    Attributes:
        image: (h, w) measured in-band radiance [W m^-2 sr^-1] of the window, noise included.
        signal: (h, w) the same without noise (truth, for evaluation; :meth:`ThermalImager.detect`
            does not read it).
        row0: first row of the window in the full frame.
        col0: first column of the window in the full frame.
        shape: (rows, cols) of the full frame.
        t: capture time [s].
        noise_sigma: noise-equivalent radiance [W m^-2 sr^-1].
        background: deep-space background radiance [W m^-2 sr^-1].
        subrays: sub-rays per pixel and axis used for this frame.
        n_rays: rays cast (sub-rays and shadow rays).
    """

    image: FloatArray
    signal: FloatArray
    row0: int
    col0: int
    shape: tuple[int, int]
    t: float
    noise_sigma: float
    background: float
    subrays: int = 1
    n_rays: int = 0

    @property
    def n_pixels(self) -> int:
        """Pixels in the window."""
        return int(self.image.size)


@dataclass(frozen=True)
class _Render:
    """A noise-free window: absolute radiance, its place in the frame, its cost."""

    signal: FloatArray
    row0: int
    col0: int
    subrays: int
    n_rays: int


# -- the imager ------------------------------------------------------------------------------------
class ThermalImager:
    """Passive LWIR camera: renders, detects and centroids a target (module docstring: the model).

    Args:
        config: camera, radiometry and detection settings.

    Example:
        >>> import numpy as np
        >>> from perception.geometry import make_T
        >>> from perception.targets import load_target
        >>> imager = ThermalImager()
        >>> det = imager.observe(load_target("iss_port"), make_T(None, [0.0, 0.0, 20_000.0]),
        ...                      np.random.default_rng(0))
        >>> round(det.snr), det.n_pixels, bool(abs(det.bearing).max() < 1e-3)
        (18, 7, True)
    """

    def __init__(self, config: ThermalImagerConfig | None = None) -> None:
        self.config = config or ThermalImagerConfig()
        c = self.config
        self._fov = (math.radians(c.fov_deg[0]), math.radians(c.fov_deg[1]))
        #: Angle from the boresight to the frame's corner [rad].
        self._half_diagonal = math.atan(
            math.hypot(math.tan(0.5 * self._fov[0]), math.tan(0.5 * self._fov[1]))
        )
        band = (float(c.band_um[0]), float(c.band_um[1]))
        self._band = band
        self._background = float(band_radiance(c.background_temperature_k, band))
        self._ner = c.netd_k * _band_radiance_derivative(c.netd_reference_k, band)
        self._last: tuple[object, bytes, bytes | None, _Render] | None = None

    # -- geometry ----------------------------------------------------------------------------------
    @property
    def ifov_rad(self) -> float:
        """Angular size of a pixel [rad] (geometric mean of the two axes)."""
        c = self.config
        return math.sqrt(self._fov[0] / c.cols * self._fov[1] / c.rows)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the full frame."""
        return self.config.rows, self.config.cols

    @property
    def noise_sigma(self) -> float:
        """Noise-equivalent radiance [W m^-2 sr^-1]: NETD times dL/dT at the reference."""
        return self._ner

    @property
    def frame_period_s(self) -> float:
        """Time between frames [s]."""
        return 1.0 / self.config.frame_rate_hz

    def pixel_direction(self, row: npt.ArrayLike, col: npt.ArrayLike) -> FloatArray:
        """Unit directions (..., 3), sensor frame, of continuous pixel positions: ``(r, c)`` is
        the top-left corner of pixel ``(r, c)``, ``(r + 0.5, c + 0.5)`` its centre (``row`` and
        ``col`` broadcast: a column and a row give the grid)."""
        c = self.config
        # angles_to_directions(az, -down) with the tangents taken before broadcasting.
        tx = np.tan((np.asarray(col, dtype=np.float64) / c.cols - 0.5) * self._fov[0])
        ty = np.tan((np.asarray(row, dtype=np.float64) / c.rows - 0.5) * self._fov[1])
        return _unit_directions(*np.broadcast_arrays(tx, ty))

    def _to_pixels(self, directions: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Continuous (row, col) of directions with z > 0 (inverse of :meth:`pixel_direction`)."""
        c = self.config
        az = np.arctan2(directions[..., 0], directions[..., 2])
        down = np.arctan2(directions[..., 1], directions[..., 2])
        return (down / self._fov[1] + 0.5) * c.rows, (az / self._fov[0] + 0.5) * c.cols

    def _footprint(self, center: FloatArray, radius: float) -> tuple[int, int, int, int] | None:
        """Pixel box ``(r0, r1, c0, c1)`` (half-open) covering the bounding sphere's projection,
        clipped to the frame; None when it misses the frame."""
        rows, cols = self.shape
        dist = float(np.linalg.norm(center))
        if dist <= radius:
            return 0, rows, 0, cols
        u = center / dist
        alpha = math.asin(radius / dist)
        off_axis = math.acos(max(-1.0, min(1.0, float(u[2]))))
        if off_axis - alpha > self._half_diagonal:
            return None  # the cone misses the field of view (or lies behind the sensor)
        if off_axis + alpha >= 0.5 * math.pi - 1e-6:
            return 0, rows, 0, cols  # the cone reaches the image plane: no bounded projection
        # Two unit vectors normal to u, then the cone's rim.
        if abs(u[0]) < 0.9:
            e1 = np.array([0.0, u[2], -u[1]]) / math.hypot(u[1], u[2])  # u x (1, 0, 0)
        else:
            e1 = np.array([-u[2], 0.0, u[0]]) / math.hypot(u[0], u[2])  # u x (0, 1, 0)
        e2 = np.array(
            [u[1] * e1[2] - u[2] * e1[1], u[2] * e1[0] - u[0] * e1[2], u[0] * e1[1] - u[1] * e1[0]]
        )
        rim = math.cos(alpha) * u + math.sin(alpha) * (_RIM_COS * e1 + _RIM_SIN * e2)
        r, c = self._to_pixels(rim)
        r0, r1 = max(math.floor(r.min()) - 1, 0), min(math.floor(r.max()) + 2, rows)
        c0, c1 = max(math.floor(c.min()) - 1, 0), min(math.floor(c.max()) + 2, cols)
        if r0 >= r1 or c0 >= c1:
            return None
        return r0, r1, c0, c1

    def _subrays(self, dist: float, radius: float) -> int:
        c = self.config
        pixel_m = max(self._fov[0] / c.cols, self._fov[1] / c.rows) * dist
        need = math.ceil(c.min_samples_across_target * pixel_m / max(2.0 * radius, 1e-9))
        return int(min(max(c.supersampling, need), c.max_supersampling))

    # -- radiometry --------------------------------------------------------------------------------
    def _face_optics(self, target: TargetModel) -> tuple[FloatArray, FloatArray]:
        """Per-face emissivity and solar absorptivity (F,)."""
        c = self.config
        n = len(target.mesh.faces)
        if c.grey_from_reflectivity:
            eps = np.clip(1.0 - target.reflectivity, 0.01, 1.0)
            return eps, eps
        return np.full(n, c.emissivity), np.full(n, c.solar_absorptivity)

    def _hit_radiance(
        self,
        target: TargetModel,
        T: FloatArray,
        d: FloatArray | None,
        face: npt.NDArray[np.int64],
        sun: FloatArray | None,
    ) -> tuple[FloatArray, int]:
        """In-band radiance (K,) of the sub-rays that hit faces ``face`` along unit directions
        ``d`` (K, 3), target frame (needed by day only), and the shadow rays cast."""
        c = self.config
        eps, alpha = self._face_optics(target)
        e = eps[face]
        if sun is None:
            temp = np.full(face.size, c.eclipse_temperature_k)
            return e * band_radiance(temp, self._band) + (1.0 - e) * self._background, 0
        normals, offsets = face_planes(target)
        assert d is not None
        o = -(T[:3, :3].T @ T[:3, 3])  # the sensor, target frame
        n_f = normals[face]
        denom = np.einsum("ij,ij->i", n_f, d)
        side = np.where(denom < 0.0, 1.0, -1.0)  # the face side the sensor sees
        mu = (n_f @ sun) * side
        lit = mu > 0.0
        n_shadow = 0
        if c.self_shadowing and lit.any():
            k = np.flatnonzero(lit & (np.abs(denom) > 1e-12))
            rng_m = (offsets[face[k]] - n_f[k] @ o) / denom[k]
            lift = 1e-4 * max(target.radius, 1e-3)  # off the surface, toward the Sun's side
            start = o + d[k] * rng_m[:, None] + lift * side[k, None] * n_f[k]
            first = target.ray.intersects_first(start, np.broadcast_to(sun, start.shape))
            lit[k[np.asarray(first) >= 0]] = False
            n_shadow = k.size
        absorbed = np.where(lit, alpha[face] * c.solar_constant_w_m2 * mu, 0.0)
        temp = np.sqrt(np.sqrt(c.shade_temperature_k**4 + absorbed / (e * SIGMA_SB)))
        return e * band_radiance(temp, self._band) + (1.0 - e) * self._background, n_shadow

    # -- rendering ---------------------------------------------------------------------------------
    def _render(self, target: TargetModel, T: FloatArray, sun: FloatArray | None) -> _Render:
        """The noise-free window (memoised for the last target, pose and Sun)."""
        key = (T.tobytes(), None if sun is None else sun.tobytes())
        if self._last is not None and self._last[0] is target and self._last[1:3] == key:
            return self._last[3]
        out = self._render_new(target, T, sun)
        self._last = (target, key[0], key[1], out)
        return out

    def subray_directions(self, target: TargetModel, T_sensor_target: npt.ArrayLike) -> FloatArray:
        """(M, 3) unit directions, sensor frame, of the sub-rays a frame at this pose casts
        (row-major over the sub-ray grid of the target's footprint; empty when nothing is in
        view): what a benchmark casts bare to compare with :meth:`capture`."""
        T, _ = self._check(target, T_sensor_target, None)
        grid = self._subray_grid(target, T)
        if grid is None:
            return np.zeros((0, 3))
        _, _, tx, ty = grid
        return _unit_directions(*np.broadcast_arrays(tx, ty)).reshape(-1, 3)

    def _subray_grid(
        self, target: TargetModel, T: FloatArray
    ) -> tuple[tuple[int, int, int, int], int, FloatArray, FloatArray] | None:
        """The footprint's pixel box, the sub-rays per pixel and axis ``n``, and the tangents
        ``x / z`` (1, w n) and ``y / z`` (h n, 1) of the sub-rays on the regular grid n times
        finer than the pixels (row-major: sub-ray ``k`` is row ``k // (w n)``)."""
        center = T[:3, 3]
        dist = float(np.linalg.norm(center))
        radius = max(target.radius, 1e-9)
        box = None if dist - radius > self.config.max_range_m else self._footprint(center, radius)
        if box is None:
            return None
        r0, r1, c0, c1 = box
        n = self._subrays(dist, radius)
        c = self.config
        sub = (np.arange(n) + 0.5) / n
        rr = (np.arange(r0, r1, dtype=np.float64)[:, None] + sub).reshape(-1, 1)  # (h n, 1)
        cc = (np.arange(c0, c1, dtype=np.float64)[:, None] + sub).reshape(1, -1)  # (1, w n)
        tx = np.tan((cc / c.cols - 0.5) * self._fov[0])
        ty = np.tan((rr / c.rows - 0.5) * self._fov[1])
        return box, n, tx, ty

    def _render_new(self, target: TargetModel, T: FloatArray, sun: FloatArray | None) -> _Render:
        c = self.config
        rows, cols = self.shape
        grid = self._subray_grid(target, T)
        if grid is None:
            return _Render(np.zeros((0, 0)), 0, 0, 0, 0)
        (r0, r1, c0, c1), n, tx, ty = grid
        # One Embree call on float32 rays in the target frame, as raycast.cast_from_sensor makes
        # it (trimesh normalises the directions); the radiance needs only the faces hit and, by
        # day, the directions of the hit rays (to place the shadow rays).
        R = T[:3, :3]
        R32 = R.astype(np.float32)
        tx32, ty32 = tx.astype(np.float32), ty.astype(np.float32)
        d32 = np.empty((ty.shape[0], tx.shape[1], 3), dtype=np.float32)
        for k in range(3):
            d32[..., k] = tx32 * R32[0, k] + ty32 * R32[1, k] + R32[2, k]
        d32 = d32.reshape(-1, 3)
        o32 = np.broadcast_to((-(R.T @ T[:3, 3])).astype(np.float32), d32.shape)
        first = np.asarray(target.ray.intersects_first(o32, d32), dtype=np.int64)
        idx = np.flatnonzero(first >= 0)
        d_hit = None
        if sun is not None:
            row, col = np.divmod(idx, tx.shape[1])
            d_hit = _unit_directions(tx[0, col], ty[row, 0]) @ R
        excess = np.zeros(d32.shape[0])
        hit_l, n_shadow = self._hit_radiance(target, T, d_hit, first[idx], sun)
        excess[idx] = hit_l - self._background
        # The optics blur the sub-ray image (point samples of the scene) and the pixels integrate
        # it: per axis, pixel i gets sample j with weight (1/n) * (Phi((i + 1 - x_j) / s) -
        # Phi((i - x_j) / s)), exact for a Gaussian PSF (blurring pixel values instead would
        # keep the pixel-phase bias of a sharp image's centroid). The window grows by the PSF's
        # reach within the frame; light beyond it falls off the detector.
        m = math.ceil(_PSF_TRUNCATE * c.psf_sigma_px)
        R0, R1, C0, C1 = max(r0 - m, 0), min(r1 + m, rows), max(c0 - m, 0), min(c1 + m, cols)
        # The weights only depend on the window's offsets from the rendered box (cached).
        A_r = _pixel_weights(R0 - r0, R1 - r0, (r1 - r0) * n, n, c.psf_sigma_px)
        A_c = _pixel_weights(C0 - c0, C1 - c0, (c1 - c0) * n, n, c.psf_sigma_px)
        blurred = A_c @ (A_r @ excess.reshape(A_r.shape[1], A_c.shape[1])).T  # (W, H)
        window = self._background + np.ascontiguousarray(blurred.T)
        window.setflags(write=False)
        return _Render(window, R0, C0, n, d32.shape[0] + n_shadow)

    # -- public API --------------------------------------------------------------------------------
    def capture(
        self,
        target: TargetModel,
        T_sensor_target: npt.ArrayLike,
        rng: np.random.Generator,
        *,
        sun_direction_target: npt.ArrayLike | None = None,
        t: float = 0.0,
    ) -> ThermalFrame:
        """One frame (its window around the target).

        Args:
            target: the target model.
            T_sensor_target: (4, 4) target pose in the sensor frame.
            rng: the only source of randomness (the pixel noise).
            sun_direction_target: (3,) unit vector from the target toward the Sun, target body
                frame; None in eclipse (night).
            t: capture time [s].

        Returns:
            The window: empty (0 x 0) when the target is behind the sensor, outside the field of
            view or beyond ``max_range_m``.

        Raises:
            ValueError: a non-finite or non-rigid pose, a bad Sun direction, time or generator.
        """
        T, sun = self._check(target, T_sensor_target, sun_direction_target)
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng={rng!r}; expected a numpy.random.Generator")  # noqa: TRY004
        t = _check_time(t)
        r = self._render(target, T, sun)
        image = r.signal + self._ner * rng.standard_normal(r.signal.shape)
        return ThermalFrame(
            image=image,
            signal=r.signal,
            row0=r.row0,
            col0=r.col0,
            shape=self.shape,
            t=t,
            noise_sigma=self._ner,
            background=self._background,
            subrays=r.subrays,
            n_rays=r.n_rays,
        )

    def detect(self, frame: ThermalFrame) -> ThermalDetection | None:
        """Threshold, label and centroid a frame (module docstring); None when no blob passes.

        Raises:
            ValueError: ``frame`` is not a :class:`ThermalFrame` or its image is not 2-D.
        """
        if not isinstance(frame, ThermalFrame):
            raise ValueError(f"frame={type(frame).__name__}; expected a ThermalFrame")  # noqa: TRY004
        img = np.asarray(frame.image, dtype=np.float64)
        if img.ndim != 2:
            raise ValueError(f"frame.image has shape {img.shape}; expected (h, w)")
        if img.size == 0:
            return None
        c = self.config
        excess = img - frame.background
        lit = excess > c.detection_threshold_sigma * frame.noise_sigma
        if not lit.any():
            return None
        labels, n_blobs = ndimage.label(lit, structure=np.ones((3, 3), dtype=bool))
        flat = labels.ravel()
        sizes = np.bincount(flat, minlength=n_blobs + 1)[1:]
        sums = np.bincount(flat, weights=excess.ravel(), minlength=n_blobs + 1)[1:]
        ok = sizes >= c.min_blob_pixels
        if not ok.any():
            return None
        best = int(np.flatnonzero(ok)[np.argmax(sums[ok])]) + 1
        # The aperture within the blob's box grown by the margin (the rest of the window is 0).
        m = c.centroid_margin_px
        rs, cs = ndimage.find_objects(labels, max_label=best)[best - 1]
        y0, y1 = max(rs.start - m, 0), min(rs.stop + m, excess.shape[0])
        x0, x1 = max(cs.start - m, 0), min(cs.stop + m, excess.shape[1])
        blob = labels[y0:y1, x0:x1] == best
        aperture = _grow(blob, m).astype(np.float64)
        sub = excess[y0:y1, x0:x1]
        fit = self._centroid(sub, aperture, frame.row0 + y0, frame.col0 + x0, frame.noise_sigma)
        if fit is None:
            return None
        direction, bearing, sigma = fit
        return ThermalDetection(
            t=float(frame.t),
            direction=direction,
            bearing=bearing,
            sigma_rad=sigma,
            snr=float(sub[blob].max() / frame.noise_sigma),
            n_pixels=int(sizes[best - 1]),
        )

    def observe(
        self,
        target: TargetModel,
        T_sensor_target: npt.ArrayLike,
        rng: np.random.Generator,
        *,
        sun_direction_target: npt.ArrayLike | None = None,
        t: float = 0.0,
    ) -> ThermalDetection | None:
        """:meth:`capture` then :meth:`detect`; None when nothing is detected (including a target
        behind the sensor, outside the field of view or beyond ``max_range_m``)."""
        frame = self.capture(
            target, T_sensor_target, rng, sun_direction_target=sun_direction_target, t=t
        )
        return self.detect(frame)

    def predicted_snr(
        self,
        target: TargetModel,
        T_sensor_target: npt.ArrayLike,
        *,
        sun_direction_target: npt.ArrayLike | None = None,
    ) -> float:
        """Peak pixel signal over the noise sigma of the noise-free frame (0 when not in view)."""
        r = self._render(target, *self._check(target, T_sensor_target, sun_direction_target))
        if r.signal.size == 0:
            return 0.0
        return float((r.signal.max() - self._background) / self._ner)

    def detection_probability(
        self,
        target: TargetModel,
        T_sensor_target: npt.ArrayLike,
        *,
        sun_direction_target: npt.ArrayLike | None = None,
    ) -> float:
        """Probability that :meth:`detect` finds a blob in a frame at this pose (module
        docstring): at least ``min_blob_pixels`` pixels above the threshold, each with
        ``Phi(s_i / NER - k)``. 0 when the target is not in view."""
        r = self._render(target, *self._check(target, T_sensor_target, sun_direction_target))
        if r.signal.size == 0:
            return 0.0
        snr = (r.signal - self._background).ravel() / self._ner
        p = ndtr(snr - self.config.detection_threshold_sigma)
        return _at_least(p, self.config.min_blob_pixels)

    def predicted_bearing_sigma_rad(
        self,
        target: TargetModel,
        T_sensor_target: npt.ArrayLike,
        *,
        sun_direction_target: npt.ArrayLike | None = None,
    ) -> float:
        """1-sigma bearing error per axis [rad] of a detection at this pose: the centroid formula
        of the module docstring on the noise-free frame, over the aperture expected under the
        noise (each pixel weighted by the probability that a lit pixel lies within
        ``centroid_margin_px`` of it). ``inf`` when the target is not in view."""
        r = self._render(target, *self._check(target, T_sensor_target, sun_direction_target))
        if r.signal.size == 0:
            return math.inf
        excess = r.signal - self._background
        p_lit = ndtr(excess / self._ner - self.config.detection_threshold_sigma)
        m = self.config.centroid_margin_px
        # P(no lit pixel within the margin) = prod (1 - p_i) over the disc: a sum of logs.
        log_dark = np.log1p(-np.minimum(p_lit, 1.0 - 1e-15))
        covered = -np.expm1(ndimage.correlate(log_dark, _disc(m).astype(np.float64)))
        fit = self._centroid(excess, covered, r.row0, r.col0, self._ner)
        return math.inf if fit is None else fit[2]

    # -- internals ---------------------------------------------------------------------------------
    def _centroid(
        self, excess: FloatArray, weight: FloatArray, row0: int, col0: int, noise_sigma: float
    ) -> tuple[FloatArray, FloatArray, float] | None:
        """Signal-weighted centroid over an aperture (``weight`` 1 inside, 0 outside; a
        probability for the expected aperture): direction, bearing and claimed sigma."""
        h, w = excess.shape
        y = np.arange(h, dtype=np.float64)[:, None] + (row0 + 0.5)
        x = np.arange(w, dtype=np.float64)[None, :] + (col0 + 0.5)
        wv = weight * excess
        s = float(wv.sum())
        if not s > 0.0:
            return None
        yc, xc = float((wv * y).sum()) / s, float((wv * x).sum()) / s
        sx = noise_sigma * math.sqrt(float((weight * (x - xc) ** 2).sum())) / s  # [pixels]
        sy = noise_sigma * math.sqrt(float((weight * (y - yc) ** 2).sum())) / s
        d = self.pixel_direction(yc, xc)
        az = math.atan2(d[0], d[2])
        el = math.atan2(-d[1], math.hypot(d[0], d[2]))
        # el = atan(tan(el_pixel) cos(az)): its derivative maps the row error to the bearing's.
        c = self.config
        tan_ep = -d[1] / d[2]
        jac = math.cos(az) * (1.0 + tan_ep**2) / (1.0 + (tan_ep * math.cos(az)) ** 2)
        s_az = sx * self._fov[0] / c.cols
        s_el = sy * self._fov[1] / c.rows * jac
        sigma = math.sqrt(0.5 * (s_az**2 + s_el**2))
        return d, np.array([az, el]), sigma

    def _check(
        self, target: TargetModel, T_sensor_target: npt.ArrayLike, sun: npt.ArrayLike | None
    ) -> tuple[FloatArray, FloatArray | None]:
        if not isinstance(target, TargetModel):
            raise ValueError(f"target={type(target).__name__}; expected a TargetModel")  # noqa: TRY004
        T = _check_pose(T_sensor_target)
        if sun is None:
            return T, None
        s = np.asarray(sun, dtype=np.float64)
        if s.shape != (3,):
            raise ValueError(
                f"sun_direction_target has shape {s.shape}; expected (3,) (or None for eclipse)"
            )
        norm = float(np.linalg.norm(s))
        if not (math.isfinite(norm) and norm > 1e-9):
            raise ValueError(
                f"sun_direction_target={s.tolist()}; expected a finite non-zero direction"
            )
        return T, s / norm


def _check_pose(T_sensor_target: npt.ArrayLike) -> FloatArray:
    arr = np.asarray(T_sensor_target, dtype=np.float64)
    if arr.shape != (4, 4):
        raise ValueError(
            f"T_sensor_target has shape {arr.shape}; expected a (4, 4) homogeneous transform"
        )
    if not np.all(np.isfinite(arr)):
        bad = arr[~np.isfinite(arr)][0]
        raise ValueError(f"T_sensor_target has a non-finite entry ({bad}); expected finite values")
    return check_rigid(arr, "T_sensor_target")


def _check_time(t: float) -> float:
    if isinstance(t, bool) or not isinstance(t, (int, float, np.floating, np.integer)):
        raise ValueError(f"t={t!r}; expected a finite time [s]")  # noqa: TRY004
    if not math.isfinite(float(t)):
        raise ValueError(f"t={t!r}; expected a finite time [s]")
    return float(t)


def _unit_directions(tx: FloatArray, ty: FloatArray) -> FloatArray:
    """Unit directions (..., 3) ``(tx, ty, 1) / norm`` from the tangents ``x / z``, ``y / z``."""
    d = np.empty((*tx.shape, 3))
    inv = 1.0 / np.sqrt(tx * tx + ty * ty + 1.0)
    d[..., 0] = tx * inv
    d[..., 1] = ty * inv
    d[..., 2] = inv
    return d


@functools.lru_cache(maxsize=64)
def _pixel_weights(lo: int, hi: int, count: int, n: int, sigma: float) -> sparse.csc_array:
    """(hi - lo, count) weights of sub-ray samples at ``x_j = (j + 0.5) / n`` [pixels] in pixels
    ``lo..hi-1`` of one axis: a Gaussian PSF of ``sigma`` pixels integrated over each pixel, times
    the sample's width ``1 / n`` (a box average when ``sigma`` is 0). Sparse, built by columns: a
    sample reaches the pixels within the PSF's reach (and a sparse product runs on one thread,
    where BLAS threads stall for milliseconds on a loaded machine). Read-only (cached)."""
    reach = math.ceil(_PSF_TRUNCATE * sigma) + 1
    x = (np.arange(count) + 0.5) / n
    pix = np.floor(x).astype(np.int64)[:, None] + np.arange(-reach, reach + 1)  # (count, K)
    if sigma > 0:
        w = ndtr((pix + 1 - x[:, None]) / sigma) - ndtr((pix - x[:, None]) / sigma)
    else:
        w = (pix == np.floor(x)[:, None]).astype(np.float64)
    inside = (pix >= lo) & (pix < hi)
    w = np.where(inside & (w > 1e-15), w / n, 0.0)  # outside the window, or subnormal tails
    k = pix.shape[1]
    return sparse.csc_array(
        (w.ravel(), np.clip(pix - lo, 0, hi - lo - 1).ravel(), np.arange(0, count * k + 1, k)),
        shape=(hi - lo, count),
    )


def _disc(radius: int) -> npt.NDArray[np.bool_]:
    """(2 radius + 1, 2 radius + 1) disc of pixels within ``radius`` of the centre."""
    r = np.arange(-radius, radius + 1)
    return np.asarray((r[:, None] ** 2 + r[None, :] ** 2) <= radius * radius)


def _grow(mask: npt.NDArray[np.bool_], margin: int) -> npt.NDArray[np.bool_]:
    """``mask`` grown by a disc of ``margin`` pixels."""
    if margin <= 0:
        return mask
    return np.asarray(ndimage.binary_dilation(mask, structure=_disc(margin)), dtype=bool)


def _at_least(p: FloatArray, m: int) -> float:
    """P(at least ``m`` of independent events with probabilities ``p`` occur) (Poisson-binomial
    tail): the generating polynomial ``prod(1 - p_i + p_i z)`` truncated to degree ``m - 1``,
    multiplied pairwise in ``log2(len(p))`` vectorised rounds."""
    p = np.clip(np.asarray(p, dtype=np.float64).ravel(), 0.0, 1.0)
    if m <= 1:
        with np.errstate(divide="ignore"):
            return float(-np.expm1(np.sum(np.log1p(-p))))
    if int(np.count_nonzero(p > 1.0 - 1e-12)) >= m:
        return 1.0
    coef = np.zeros((p.size, m))
    coef[:, 0] = 1.0 - p
    coef[:, 1] = p
    # Pairwise products of polynomials, coefficients above degree m - 1 dropped: the outer
    # product's terms i + j < m summed into degree i + j by a 0/1 matrix.
    i_idx, j_idx = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    keep = (i_idx + j_idx) < m
    to_degree = np.zeros((int(keep.sum()), m))
    to_degree[np.arange(to_degree.shape[0]), (i_idx + j_idx)[keep]] = 1.0
    while coef.shape[0] > 1:
        if coef.shape[0] % 2:
            coef = np.vstack([coef, np.eye(1, m)])  # the polynomial 1
        a, b = coef[0::2], coef[1::2]
        coef = (a[:, :, None] * b[:, None, :])[:, keep] @ to_degree
    return float(min(max(1.0 - coef[0].sum(), 0.0), 1.0))
