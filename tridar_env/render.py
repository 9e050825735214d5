"""Two-panel rendering in the spirit of the seed-000 crew displays (Fig. 12).

Left: the trajectory in the Hill frame (V-bar horizontal, R-bar vertical) with the approach
corridor, the true chaser path and the path implied by the TriDAR estimate. Right: a centreline
camera view from the TriDAR — the target ray-cast with Embree and Lambert-shaded — with the last
scan's points in red and mode, range, range rate and estimation errors as text.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg", force=False)
import matplotlib.pyplot as plt
import numpy as np
import numpy.typing as npt
from matplotlib.backends.backend_agg import FigureCanvasAgg

from perception.geometry import invert

if TYPE_CHECKING:
    from tridar_env.env import DockingEnv

CAMERA_PIXELS = 128


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
    """Draws frames of a :class:`DockingEnv` with matplotlib's Agg canvas (headless)."""

    def __init__(self, env: DockingEnv) -> None:
        self.env = env
        self.fig = plt.figure(figsize=(9.6, 4.8), dpi=80)
        self.canvas = FigureCanvasAgg(self.fig)
        self._window: Any = None

    def draw(self) -> npt.NDArray[np.uint8]:
        env = self.env
        w = env.world
        self.fig.clf()
        ax1 = self.fig.add_subplot(1, 2, 1)
        ax2 = self.fig.add_subplot(1, 2, 2)
        # --- trajectory in the Hill frame: y (V-bar) horizontal, x (R-bar up) vertical
        hist = env.history
        r = np.array([h["r"] for h in hist]) if hist else w.state[None, :3]
        ax1.plot(r[:, 1], r[:, 0], "-", color="k", lw=1.2, label="true")
        est = [h["est_r"] for h in hist if h["est_r"] is not None]
        if est:
            e = np.array(est)
            ax1.plot(e[:, 1], e[:, 0], ".", color="tab:red", ms=2, label="TriDAR estimate")
        port = w.T_lvlh_port
        axis = port[:3, 2]
        half = np.radians(env.cfg.env.corridor_half_angle_deg or env.cfg.pipeline.corridor.half_angle_deg)
        L = max(float(np.linalg.norm(r[0] - port[:3, 3])) * 1.1, 5.0)
        perp = np.cross(axis, [0.0, 0.0, 1.0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.array([1.0, 0.0, 0.0])
        perp /= np.linalg.norm(perp)
        for s in (-1, 1):
            tip = port[:3, 3] + L * (axis * np.cos(half) + s * perp * np.sin(half))
            ax1.plot([port[1, 3], tip[1]], [port[0, 3], tip[0]], "--", color="tab:green", lw=0.8)
        bounds = env.target.bounds
        ax1.add_patch(plt.Rectangle((bounds[0][1], bounds[0][0]), *(bounds[1] - bounds[0])[[1, 0]],
                                    color="0.7", alpha=0.5))
        ax1.plot(r[-1, 1], r[-1, 0], "o", color="tab:blue", ms=5, label="chaser")
        ax1.set_xlabel("V-bar y [m]")
        ax1.set_ylabel("R-bar x [m]")
        ax1.set_title("Hill frame")
        ax1.set_aspect("equal", adjustable="datalim")
        ax1.legend(loc="upper right", fontsize=7)
        # --- centreline camera from the TriDAR
        truth = w.sensor_truth()
        fov = env.cfg.sensor.fov_deg
        img = camera_image(env.target, truth.T_sensor_target, fov)
        ext = [-fov[0] / 2, fov[0] / 2, fov[1] / 2, -fov[1] / 2]
        ax2.imshow(img, cmap="gray", vmin=0, vmax=1, extent=ext)
        cloud = env.observer.last_cloud
        pts = getattr(cloud, "points", None)
        if pts is not None and len(pts):
            az = np.degrees(np.arctan2(pts[:, 0], pts[:, 2]))
            el = np.degrees(np.arctan2(pts[:, 1], pts[:, 2]))
            ax2.plot(az, el, ".", color="red", ms=1.5)
        sv = env.state_vector
        h = hist[-1] if hist else {}
        lines = [f"mode {h.get('mode', '-')}", f"t {w.t:7.1f} s"]
        if sv is not None and sv.valid.range:
            lines.append(f"range {sv.range:7.2f} m  rate {sv.range_rate:+.3f} m/s")
        if h and np.isfinite(h.get("pos_err", np.nan)):
            lines.append(f"err {100 * h['pos_err']:.1f} cm / {h['att_err']:.2f} deg")
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
