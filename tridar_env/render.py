"""Two-panel rendering in the spirit of the seed-000 crew displays (Fig. 12).

Left: the trajectory in the Hill frame (V-bar horizontal, R-bar vertical) with the approach
corridor, the true chaser path and the path implied by the TriDAR estimate. Right: a centreline
camera view from the TriDAR — the target ray-cast with Embree and Lambert-shaded — with the last
scan's points in red and mode, range, range rate and estimation errors as text.

The renderer draws a :class:`RenderState`, the frame's content gathered by the environment; it
does not know the environment.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg", force=False)
import matplotlib.pyplot as plt
import numpy as np
import numpy.typing as npt
from matplotlib.backends.backend_agg import FigureCanvasAgg

from perception.geometry import invert

if TYPE_CHECKING:
    from perception.targets import TargetModel

FloatArray = npt.NDArray[np.float64]

CAMERA_PIXELS = 128


@dataclass(frozen=True)
class RenderState:
    """What one frame shows (truth unless named an estimate), LVLH / Hill frame.

    Attributes:
        t: Simulation time [s].
        r_lvlh: ``(T, 3)`` true chaser positions so far, oldest first [m].
        est_r_lvlh: ``(E, 3)`` chaser positions implied by the TriDAR estimate [m]; ``None``
            when no step had a valid estimate.
        T_lvlh_port: ``(4, 4)`` docking port pose.
        corridor_half_angle_deg: Half angle of the approach corridor drawn at the port [deg].
        target: The target model (its mesh, ray caster and bounds).
        T_sensor_target: ``(4, 4)`` true target pose in the TriDAR frame.
        fov_deg: Sensor field of view ``(az, el)`` [deg].
        cloud_points: ``(N, 3)`` last scan's points in the sensor frame [m]; ``None`` if none.
        mode: Pipeline mode of the last step (``"-"`` before any).
        range_m: Estimated range [m]; ``None`` when the estimate has no valid range.
        range_rate_m_s: Estimated range rate [m/s]; ``None`` with ``range_m``.
        pos_err_m: Estimated position error of the last step [m]; NaN if not valid.
        att_err_deg: Estimated attitude error of the last step [deg]; NaN if not valid.
    """

    t: float
    r_lvlh: FloatArray
    est_r_lvlh: FloatArray | None
    T_lvlh_port: FloatArray
    corridor_half_angle_deg: float
    target: TargetModel
    T_sensor_target: FloatArray
    fov_deg: tuple[float, float]
    cloud_points: FloatArray | None
    mode: Any
    range_m: float | None
    range_rate_m_s: float | None
    pos_err_m: float
    att_err_deg: float


def camera_image(target: Any, T_sensor_target: npt.NDArray[np.float64], fov_deg: tuple[float, float],
                 pixels: int = CAMERA_PIXELS) -> npt.NDArray[np.float64]:
    """Shaded (pixels, pixels) image of the target from the sensor; 0 = background, (0, 1] = hit."""
    ax = np.tan(np.radians(fov_deg[0]) / 2)
    ay = np.tan(np.radians(fov_deg[1]) / 2)
    u = np.linspace(-ax, ax, pixels)
    v = np.linspace(-ay, ay, pixels)
    uu, vv = np.meshgrid(u, v)
    d_s = np.column_stack([uu.ravel(), vv.ravel(), np.ones(uu.size)])
    d_s /= np.linalg.norm(d_s, axis=1, keepdims=True)
    T_ts = invert(T_sensor_target)
    d_t = d_s @ T_ts[:3, :3].T
    o_t = np.broadcast_to(T_ts[:3, 3], d_t.shape)
    img = np.zeros(uu.size)
    tri, ray = target.ray.intersects_id(o_t, d_t, multiple_hits=False, return_locations=False)
    if len(tri):
        n = target.mesh.face_normals[tri]
        img[ray] = 0.15 + 0.85 * np.abs(np.einsum("ij,ij->i", n, d_t[ray]))
    return img.reshape(pixels, pixels)


class Renderer:
    """Draws :class:`RenderState` frames with matplotlib's Agg canvas (headless)."""

    def __init__(self) -> None:
        self.fig = plt.figure(figsize=(9.6, 4.8), dpi=80)
        self.canvas = FigureCanvasAgg(self.fig)
        self._window: Any = None

    def draw(self, state: RenderState) -> npt.NDArray[np.uint8]:
        """Draw ``state``; returns the ``(H, W, 3)`` RGB frame."""
        self.fig.clf()
        ax1 = self.fig.add_subplot(1, 2, 1)
        ax2 = self.fig.add_subplot(1, 2, 2)
        # --- trajectory in the Hill frame: y (V-bar) horizontal, x (R-bar up) vertical
        r = state.r_lvlh
        ax1.plot(r[:, 1], r[:, 0], "-", color="k", lw=1.2, label="true")
        if state.est_r_lvlh is not None:
            e = state.est_r_lvlh
            ax1.plot(e[:, 1], e[:, 0], ".", color="tab:red", ms=2, label="TriDAR estimate")
        port = state.T_lvlh_port
        axis = port[:3, 2]
        half = np.radians(state.corridor_half_angle_deg)
        L = max(float(np.linalg.norm(r[0] - port[:3, 3])) * 1.1, 5.0)
        perp = np.cross(axis, [0.0, 0.0, 1.0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.array([1.0, 0.0, 0.0])
        perp /= np.linalg.norm(perp)
        for s in (-1, 1):
            tip = port[:3, 3] + L * (axis * np.cos(half) + s * perp * np.sin(half))
            ax1.plot([port[1, 3], tip[1]], [port[0, 3], tip[0]], "--", color="tab:green", lw=0.8)
        bounds = state.target.bounds
        ax1.add_patch(plt.Rectangle((bounds[0][1], bounds[0][0]), *(bounds[1] - bounds[0])[[1, 0]],
                                    color="0.7", alpha=0.5))
        ax1.plot(r[-1, 1], r[-1, 0], "o", color="tab:blue", ms=5, label="chaser")
        ax1.set_xlabel("V-bar y [m]")
        ax1.set_ylabel("R-bar x [m]")
        ax1.set_title("Hill frame")
        ax1.set_aspect("equal", adjustable="datalim")
        ax1.legend(loc="upper right", fontsize=7)
        # --- centreline camera from the TriDAR
        fov = state.fov_deg
        img = camera_image(state.target, state.T_sensor_target, fov)
        ext = [-fov[0] / 2, fov[0] / 2, fov[1] / 2, -fov[1] / 2]
        ax2.imshow(img, cmap="gray", vmin=0, vmax=1, extent=ext)
        pts = state.cloud_points
        if pts is not None and len(pts):
            az = np.degrees(np.arctan2(pts[:, 0], pts[:, 2]))
            el = np.degrees(np.arctan2(pts[:, 1], pts[:, 2]))
            ax2.plot(az, el, ".", color="red", ms=1.5)
        lines = [f"mode {state.mode}", f"t {state.t:7.1f} s"]
        if state.range_m is not None:
            lines.append(f"range {state.range_m:7.2f} m  rate {state.range_rate_m_s:+.3f} m/s")
        if np.isfinite(state.pos_err_m):
            lines.append(f"err {100 * state.pos_err_m:.1f} cm / {state.att_err_deg:.2f} deg")
        ax2.text(0.02, 0.98, "\n".join(lines), transform=ax2.transAxes, va="top", ha="left",
                 color="yellow", fontsize=8, family="monospace")
        ax2.set_xlabel("az [deg]")
        ax2.set_ylabel("el [deg] (down +)")
        ax2.set_title("TriDAR centreline view")
        self.fig.tight_layout()
        self.canvas.draw()
        buf = np.asarray(self.canvas.buffer_rgba())
        return np.ascontiguousarray(buf[..., :3])

    def show(self, frame: npt.NDArray[np.uint8]) -> None:
        """Show a frame in a window when a display exists (``render_mode="human"``)."""
        if self._window is None:
            plt.ion()
            self._window = plt.figure("tridar-env")
            self._ax = self._window.add_subplot(1, 1, 1)
            self._ax.axis("off")
            self._img = self._ax.imshow(frame)
        else:
            self._img.set_data(frame)
        self._window.canvas.draw_idle()
        plt.pause(1e-3)

    def close(self) -> None:
        plt.close(self.fig)
        if self._window is not None:
            plt.close(self._window)
