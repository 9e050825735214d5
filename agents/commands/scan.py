"""``tridar-env scan``: simulate one TriDAR (or flash) frame of a target, save PLY + PNG picture."""

from __future__ import annotations

import argparse
from pathlib import Path

from agents.cli import command

REGIONS = ("whole", "docking_area", "port", "fov")


@command("scan", "simulate one sensor frame of a target; write a PLY point cloud and a PNG picture")
def add(p: argparse.ArgumentParser) -> None:
    p.add_argument("--target", default="cygnss", help="library name or mesh file (default cygnss)")
    p.add_argument("--port", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="docking port position of a mesh file target, file frame after --scale "
                   "[m] (give with --axis; default: placed on the +z face, with a warning)")
    p.add_argument("--axis", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="outward approach axis of the port of a mesh file target (with --port)")
    p.add_argument("--scale", type=float, default=None,
                   help="uniform scale of a mesh file target, e.g. 0.001 for millimetres")
    p.add_argument("--range", dest="range_m", type=float, default=20.0, help="range to the target's "
                   "docking port, which sits on the boresight facing the sensor [m] (default 20)")
    p.add_argument("--pattern", default=None, help="lissajous, rosette, spiral or raster "
                   "(default: the config's)")
    p.add_argument("--points", type=int, default=None, help="samples per frame (default: config)")
    p.add_argument("--region", choices=REGIONS, default="whole",
                   help="region of interest to steer the pattern onto, or the full fov")
    p.add_argument("--rpy-deg", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                   metavar=("ROLL", "PITCH", "YAW"),
                   help="extra target attitude after turning its port toward the sensor [deg]")
    p.add_argument("--spin-deg-s", type=float, default=0.0,
                   help="target spin about the boresight during the scan [deg/s]")
    p.add_argument("--frame", type=int, default=0, help="frame index (pattern phase, faults)")
    p.add_argument("--flash", action="store_true", help="use the seed-003 flash LiDAR instead")
    p.add_argument("--config", default=None, help="mission YAML whose sensor/flash sections apply")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("-o", "--output", default="scan.ply", help="PLY path; the PNG goes next to it")
    p.add_argument("--force", action="store_true",
                   help="replace an existing PLY/PNG of that name (refused otherwise)")
    p.set_defaults(handler=run)


def _target_options(args: argparse.Namespace) -> dict:
    """``load_target`` keywords from ``--port``/``--axis``/``--scale`` (mesh file targets only)."""
    if (args.port is None) != (args.axis is None):
        raise ValueError("--port and --axis must be given together")
    given = [f"--{k}" for k in ("port", "axis", "scale") if getattr(args, k) is not None]
    if not Path(args.target).suffix:
        if given:
            raise ValueError(f"{' '.join(given)}: only for a mesh file target; {args.target!r} "
                             "is a library target")
        return {}
    opts: dict = {}
    if args.port is not None:
        opts["port"] = (tuple(args.port), tuple(args.axis))
    if args.scale is not None:
        opts["scale"] = args.scale
    return opts


def _pose(target, range_m: float, rpy_deg) -> object:
    import numpy as np
    from scipy.spatial.transform import Rotation

    from perception.geometry import make_T

    if not (np.isfinite(range_m) and range_m > 0):
        raise ValueError(f"--range {range_m}; expected a positive range [m]")
    # Turn the port's approach axis toward the sensor (sensor -z), then apply the extra attitude.
    face, _ = Rotation.align_vectors([[0.0, 0.0, -1.0]], [target.port_axis])
    R = Rotation.from_euler("xyz", rpy_deg, degrees=True) * face
    return make_T(R, np.array([0.0, 0.0, range_m]) - R.apply(target.port_position))


def run(args: argparse.Namespace) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    import trimesh

    from perception.config import load_config
    from perception.sensing.pointcloud import Subsystem
    from perception.sensing.scan_patterns import angles_to_directions, directions_to_angles
    from perception.sensing.sensors import FlashLidar, RelativeMotion, TriDARSensor
    from perception.sensing.sensors.raycast import cast_rays
    from perception.targets import load_target

    cfg = load_config(args.config)
    target = load_target(args.target, **_target_options(args))
    T = _pose(target, args.range_m, args.rpy_deg)
    rng = np.random.default_rng(args.seed)
    if args.flash:
        cloud = FlashLidar(cfg.flash).capture(target, T, rng)
        half = np.radians(np.asarray(cfg.flash.fov_deg)) / 2
        lo, hi = -half, half
        label = f"flash {cfg.flash.rows}x{cfg.flash.cols}"
    else:
        sensor = TriDARSensor(cfg.sensor)
        region = None if args.region == "fov" else target.regions[args.region]
        pattern = sensor.make_scan_pattern(
            args.frame, T if region is not None else None, region, name=args.pattern,
            n_points=args.points,
        )
        motion = None
        if args.spin_deg_s:
            motion = RelativeMotion(T, np.zeros(3), np.array([0, 0, np.radians(args.spin_deg_s)]))
        cloud = sensor.scan(target, T, pattern, rng, motion=motion, frame_index=args.frame)
        lo, hi = pattern.angular_box()
        label = f"{pattern.name} {len(pattern)} samples in {pattern.duration * 1e3:.0f} ms"

    out = Path(args.output)
    existing = [q for q in (out, out.with_suffix(".png")) if q.exists()]
    folder = next((q for q in existing if q.is_dir()), None)
    if folder is not None:
        raise ValueError(f"{folder} is a folder; expected a file path for -o")
    if existing and not args.force:
        raise ValueError(f"{', '.join(map(str, existing))} exists; pass --force to replace it or "
                         "choose another -o")
    out.parent.mkdir(parents=True, exist_ok=True)
    colors = np.zeros((len(cloud), 4), dtype=np.uint8)
    colors[:, 3] = 255
    colors[:, 0] = np.where(cloud.subsystem == Subsystem.TRIANGULATION, 230, 40)
    colors[:, 2] = np.where(cloud.subsystem == Subsystem.TRIANGULATION, 40, 230)
    colors[:, 1] = np.clip(cloud.intensity * 255, 0, 255).astype(np.uint8)
    trimesh.PointCloud(cloud.points, colors=colors).export(out)

    # Picture: the target's silhouette (ray cast on a fine grid) under the points, in az/el.
    pad = 0.15 * np.maximum(hi - lo, np.radians(0.5))
    glo, ghi = lo - pad, hi + pad
    g = 300
    AZ, EL = np.meshgrid(np.linspace(glo[0], ghi[0], g), np.linspace(glo[1], ghi[1], g))
    dirs = angles_to_directions(AZ.ravel(), EL.ravel())
    R, p = T[:3, :3], T[:3, 3]
    _, rng_grid, _ = cast_rays(target, -(R.T @ p), dirs @ R)
    silhouette = np.isfinite(rng_grid).reshape(g, g)
    fig, ax = plt.subplots(figsize=(7, 6), dpi=110)
    ext = np.degrees([glo[0], ghi[0], glo[1], ghi[1]])
    ax.imshow(silhouette, origin="lower", extent=ext, cmap="Greys", alpha=0.35, aspect="equal")
    if len(cloud):
        az, el = directions_to_angles(cloud.points)
        vmin, vmax = float(cloud.ranges.min()), float(cloud.ranges.max())
        for sub, marker in ((Subsystem.TRIANGULATION, "o"), (Subsystem.TOF, "^"),
                            (Subsystem.FLASH, ".")):
            m = cloud.subsystem == sub
            if m.any():
                sc = ax.scatter(np.degrees(az[m]), np.degrees(el[m]), c=cloud.ranges[m], s=4,
                                marker=marker, cmap="viridis", vmin=vmin, vmax=vmax, label=f"{sub.name.lower()} ({m.sum()})")
        fig.colorbar(sc, ax=ax, label="range [m]")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_xlabel("azimuth [deg] (+x, right)")
    ax.set_ylabel("elevation [deg] (-y, up)")
    ax.set_title(f"{target.name} at {args.range_m:g} m: {label}, {len(cloud)} points")
    png = out.with_suffix(".png")
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)
    counts = ", ".join(f"{s.name.lower()} {cloud.count(s)}" for s in Subsystem if cloud.count(s))
    print(f"{len(cloud)} points ({counts or 'none'}) -> {out}, {png}")
    return 0
