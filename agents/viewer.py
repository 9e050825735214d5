"""The 3D viewer of a recording (``rerun-sdk``, the ``view`` extra): ``tridar-env view FILE.mcap``.

What it shows, on the timeline ``sim_time`` (simulation time of the recording, episodes one after
the other as in the file):

=================================  ====================================================================
entity                             what
=================================  ====================================================================
``sensor``                         the TriDAR frame (+z boresight, +x right, +y down: ``RDF``)
``sensor/target_truth/mesh``       the target mesh at its true pose (grey)
``sensor/target_estimate/mesh``    the target mesh at the published pose (green valid, orange degraded)
``sensor/points``                  the frame's scan points coloured by subsystem (triangulation blue,
                                   time of flight red, flash purple)
``sensor/scan_region``             the scan window: the four corner rays of the pattern's az/el box
``lvlh/chaser``                    the chaser's true position in the target's LVLH frame
``lvlh/chaser_path``               its path so far (every tenth step)
``lvlh/target``                    the target's centre of mass (LVLH origin)
``plots/position_error_m``         position error of the published pose [m]
``plots/attitude_error_deg``       attitude error [deg]
``plots/protection_level_m``       protection level [m]
``plots/mode``                     0 bearing, 1 search, 2 tracking
``log/mode``                       a line at each mode change
=================================  ====================================================================

``--save FILE.rrd`` writes the viewer's file without opening a window (tests and CI use it); the
``rerun`` viewer opens it later (``rerun FILE.rrd``).
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from perception.config import MissionConfig

__all__ = ["ENTITY_PATHS", "log_recording"]

#: The entity paths a recording's view holds (those with data in it).
ENTITY_PATHS = (
    "sensor", "sensor/target_truth", "sensor/target_truth/mesh", "sensor/target_estimate",
    "sensor/target_estimate/mesh", "sensor/points", "sensor/scan_region", "lvlh/chaser", "lvlh/chaser_path",
    "lvlh/target", "plots/position_error_m", "plots/attitude_error_deg", "plots/protection_level_m",
    "plots/mode", "log/mode",
)
_SUBSYSTEM_RGB = np.array([[40, 110, 255], [230, 50, 40], [150, 60, 200]], dtype=np.uint8)
_MODES = {"bearing": 0, "search": 1, "tracking": 2}


def require_rerun() -> Any:
    try:
        import rerun as rr
    except ImportError as exc:
        raise ValueError(f"the viewer needs the 'view' extra ({exc}); pip install 'tridar-env[view]'") from None
    return rr


def require_window() -> None:
    """A ``ValueError`` (one line) unless a viewer window can open: the extra and a display."""
    require_rerun()
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise ValueError("no display for the viewer window (DISPLAY and WAYLAND_DISPLAY unset); "
                         "record with --record FILE.mcap, then tridar-env view FILE.mcap --save FILE.rrd "
                         "and open that where there is a display (rerun FILE.rrd)")


def _T_from_pose(msg: Any) -> np.ndarray:
    from perception.geometry import T_from_quat_pos

    p, q = msg.position, msg.orientation
    return T_from_quat_pos(np.array([q.w, q.x, q.y, q.z]), np.array([p.x, p.y, p.z]))


def _region_rays(r: dict[str, Any], length: float) -> list[np.ndarray]:
    """Rays from the sensor origin through the corners of the az/el window, ``length`` [m]."""
    out = []
    for az, el in ((r["az_min"], r["el_min"]), (r["az_max"], r["el_min"]),
                   (r["az_max"], r["el_max"]), (r["az_min"], r["el_max"])):
        # az toward +x, el toward -y (up); +z boresight.
        d = np.array([math.tan(az), -math.tan(el) * math.hypot(1.0, math.tan(az)), 1.0])
        out.append(np.vstack([np.zeros(3), length * d / np.linalg.norm(d)]))
    corners = np.array([ray[1] for ray in out])
    out.append(np.vstack([corners, corners[:1]]))
    return out


def log_recording(path: str | Path, rec: Any, *, config: MissionConfig | None = None) -> dict[str, int]:
    """Log a tridar-env recording to the rerun recording stream ``rec``; counts per entity.

    Args:
        path: the ``.mcap`` recording.
        rec: a ``rerun.RecordingStream``.
        config: the mission config for the target mesh (default: the recorded one).
    """
    rr = require_rerun()
    from tridar_env.env import make_target
    from tridar_env.mcap_log import CONFIG_ATTACHMENT, read_mcap
    from tridar_env.ros2msgs import cloud_arrays

    c = read_mcap(path)
    if config is None:
        text = c.attachments.get(CONFIG_ATTACHMENT)
        if text is None:
            raise ValueError(f"{path}: no {CONFIG_ATTACHMENT} attachment; expected a tridar-env recording")
        config = MissionConfig.model_validate_json(text)
    target = make_target(config)
    mesh = target.mesh
    counts: dict[str, int] = {}

    def log(entity: str, obj: Any, static: bool = False) -> None:
        rec.log(entity, obj, static=static)
        counts[entity] = counts.get(entity, 0) + 1

    log("sensor", rr.ViewCoordinates.RDF, static=True)
    log("lvlh/target", rr.Points3D([[0.0, 0.0, 0.0]], radii=0.3, colors=[[200, 200, 200]]), static=True)
    for name, rgb in (("target_truth", [170, 170, 170, 120]), ("target_estimate", [60, 200, 90, 160])):
        log(f"sensor/{name}/mesh", rr.Mesh3D(vertex_positions=mesh.vertices, triangle_indices=mesh.faces,
                                             albedo_factor=rgb), static=True)
    path_pts: list[list[float]] = []
    last_mode = None
    last_range = 10.0
    for m in c.messages:
        t = m.log_time * 1e-9
        rec.set_time("sim_time", duration=t)
        d = m.data
        if m.topic == "/truth/pose":
            T = _T_from_pose(d.pose)
            last_range = float(np.linalg.norm(T[:3, 3]))
            log("sensor/target_truth", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        elif m.topic == "/tridar/estimate":
            T = _T_from_pose(d.pose.pose)
            log("sensor/target_estimate", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        elif m.topic == "/tridar/points":
            f = cloud_arrays(d)
            pts = np.column_stack([f["x"], f["y"], f["z"]])
            sub = np.clip(f.get("subsystem", np.zeros(len(pts))).astype(int), 0, 2)
            log("sensor/points", rr.Points3D(pts, colors=_SUBSYSTEM_RGB[sub], radii=0.02))
        elif m.topic == "/tridar/scan_region" and "az_min" in d:
            log("sensor/scan_region", rr.LineStrips3D(_region_rays(d, 1.2 * last_range),
                                                       colors=[[255, 210, 0]]))
        elif m.topic == "/tridar/state":
            log("plots/protection_level_m", rr.Scalars(d["protection_level"]))
            mode = d["mode"]
            log("plots/mode", rr.Scalars(_MODES.get(mode, -1)))
            if mode != last_mode:
                log("log/mode", rr.TextLog(f"mode {mode}"))
                last_mode = mode
            if not d["valid"]["position"]:
                rec.log("sensor/target_estimate", rr.Transform3D(scale=0.0))  # hide: no pose
        elif m.topic == "/env/step":
            if d.get("step") == 0:
                path_pts = []
            path_pts.append(d["r_lvlh"])
            log("lvlh/chaser", rr.Points3D([d["r_lvlh"]], radii=0.4, colors=[[90, 160, 255]]))
            if len(path_pts) % 10 == 1 or d.get("terminated") or d.get("truncated"):
                log("lvlh/chaser_path", rr.LineStrips3D([path_pts], colors=[[90, 160, 255]]))
            if d.get("pos_err_m") is not None:
                log("plots/position_error_m", rr.Scalars(d["pos_err_m"]))
            if d.get("att_err_deg") is not None:
                log("plots/attitude_error_deg", rr.Scalars(d["att_err_deg"]))
    return counts


def view(path: str | Path, save: str | Path | None = None, *, force: bool = False) -> dict[str, int]:
    """Show a recording in the rerun viewer, or write it to ``save`` (an ``.rrd``) without one."""
    rr = require_rerun()
    from tridar_env.mcap_log import refuse_existing

    out = refuse_existing(save, force) if save is not None else None
    if out is None:
        require_window()
    rec = rr.RecordingStream("tridar-env", recording_id=f"tridar-env:{Path(path).name}")
    if out is not None:
        rec.save(out)
    else:
        rec.spawn()
    try:
        counts = log_recording(path, rec)
    finally:
        # A viewer that went away must not hold the command up.
        rec.flush(timeout_sec=1e38 if out is not None else 10.0)
        if out is not None:
            rec.disconnect()
    return counts
