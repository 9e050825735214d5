"""``tridar-env check-target MESH --port X Y Z --axis X Y Z``: is TriDAR navigation ready for this spacecraft?

A readiness report for a user's own model, in five parts:

a. **validation**: the mesh is loaded as the env will load it (:func:`perception.targets.load_target`;
   a refusal is one line and exit code 2), with its size, face count, the port's distance to the
   surface and the symmetries found (poses a full view cannot tell apart);
b. **PAH database**: build time of the acquisition database (``cfg.pipeline.pah``);
c. **observability map**: at distances to go along the nominal approach (docking interface to port;
   the sensor sits behind the interface, where the chaser mounts it), the predicted 1-sigma bound of one
   tracking frame at the docking port (position) and on the attitude, for the region the mission's
   scan strategy picks and for the one the observability planner would pick
   (:mod:`perception.pipeline.observability`), which axes are unobserved, and whether the predicted
   protection level exceeds the alert limit (the pose would be published degraded); and the
   registrations' correlated error calibrated on the model
   (:mod:`perception.pipeline.calibration`) beside the protection level's allowance;
d. **closed loop** (unless ``--no-campaign``): ``--runs`` approaches of the stock ``final_approach``
   mission with the glideslope controller on truth and as many on the full pipeline, with the
   integrity figures of :mod:`agents.benchmarks.integrity` (docked, HMI/MI frames, maximum errors,
   where the pose was degraded);
e. **verdict**: READY, DEGRADED (with where and why) or NOT READY (with the reasons).

Files in ``--out`` (a new folder): ``report.txt``, ``observability.csv``, ``observability.png``,
``accuracy_calibration.csv`` and, with the campaign, ``campaign_runs.csv``, ``campaign_rows.json`` and ``error_vs_pl.png``.
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agents.cli import command

#: Marker kind of a check-target report folder (:mod:`agents.outputs`).
KIND = "check-target"
#: Distances from the chaser's docking interface to the port along the nominal approach for the
#: observability map [m] (the sensor sits behind the interface: its range to the port is larger).
MAP_RANGES_M = (30.0, 20.0, 10.0, 5.0, 3.0, 2.0, 1.0)
#: "Close in" for the verdict: inside this range an unobserved axis is a problem [m].
CLOSE_IN_M = 5.0  # docking interface to port [m]


@command("check-target", "readiness report for your own spacecraft mesh: validation, symmetries, "
         "PAH build, observability map, short closed-loop campaign, verdict")
def add(p: argparse.ArgumentParser) -> None:
    p.add_argument("mesh", help="mesh file (STL/OBJ/PLY/OFF/GLB/glTF) or a library target name")
    p.add_argument("--port", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="docking port position in the file's frame after --scale [m] (with --axis)")
    p.add_argument("--axis", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="outward approach axis of the port (with --port)")
    p.add_argument("--scale", type=float, default=None, help="uniform scale, e.g. 0.001 for millimetres")
    p.add_argument("--runs", type=int, default=8, help="closed-loop runs on truth and on the pipeline (default 8)")
    p.add_argument("--seeds-offset", type=int, default=0, help="run i uses reset seed offset + i")
    p.add_argument("--max-steps", type=int, default=None, help="cap on env steps per run (default: mission's)")
    p.add_argument("--no-campaign", action="store_true", help="skip the closed-loop campaign (part d)")
    p.add_argument("--out", type=Path, default=None,
                   help="report folder (default reports/check-target-<name>-<UTC time>/; always a new folder)")
    p.set_defaults(handler=run)


# --------------------------------------------------------------------------- (a) validation
def load_checked(args: argparse.Namespace) -> tuple[Any, list[str]]:
    """Load the target as the env will; any refusal becomes one ``ValueError`` line naming the file.

    Returns:
        ``(target, warnings)``: the loaded :class:`~perception.targets.TargetModel` and the
        loader's warnings (one line each).
    """
    from perception.targets import load_target

    if (args.port is None) != (args.axis is None):
        raise ValueError("--port and --axis must be given together")
    opts: dict[str, Any] = {}
    if Path(args.mesh).suffix:
        if args.port is not None:
            opts["port"] = (tuple(args.port), tuple(args.axis))
        if args.scale is not None:
            opts["scale"] = args.scale
    elif args.port is not None or args.scale is not None:
        raise ValueError(f"--port/--axis/--scale: only for a mesh file; {args.mesh!r} is a library target")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            target = load_target(args.mesh, **opts)
        except (ValueError, FileNotFoundError) as exc:
            raise ValueError(" ".join(str(exc).split())) from None
        except Exception as exc:  # a reader's own error (corrupt file): still one line, naming it
            raise ValueError(f"{args.mesh}: cannot be loaded: {' '.join(str(exc).split())}") from None
    return target, [" ".join(str(w.message).split()) for w in caught]


def _rotation_text(R: Any) -> str:
    import numpy as np
    from scipy.spatial.transform import Rotation

    rv = Rotation.from_matrix(R).as_rotvec()
    ang = float(np.linalg.norm(rv))
    ax = rv / ang if ang > 1e-12 else np.array([0.0, 0.0, 1.0])
    return f"{math.degrees(ang):.0f} deg about ({ax[0]:+.2f}, {ax[1]:+.2f}, {ax[2]:+.2f})"


def describe_target(target: Any) -> list[str]:
    """Size, faces, port and symmetries of a loaded target (report lines)."""
    import numpy as np

    mesh = target.mesh
    ext = np.asarray(mesh.extents, dtype=float)
    p = np.asarray(target.port_position, dtype=float)
    d = float(mesh.nearest.on_surface(p[None, :])[1][0])
    lines = [
        f"  size {ext[0]:.3f} x {ext[1]:.3f} x {ext[2]:.3f} m, {len(mesh.faces)} faces, "
        f"watertight {bool(mesh.is_watertight)}",
        f"  port at ({p[0]:+.3f}, {p[1]:+.3f}, {p[2]:+.3f}) m (centre-of-mass frame), axis "
        f"({target.port_axis[0]:+.2f}, {target.port_axis[1]:+.2f}, {target.port_axis[2]:+.2f}), "
        f"{1e3 * d:.1f} mm from the surface",
    ]
    dev = float(getattr(target, "simplification_deviation_m", 0.0) or 0.0)
    if getattr(target, "simplified_mesh", None) is not None:
        lines.append(f"  model simplified to {len(target.model_mesh.faces)} faces "
                     f"(deviation {1e3 * dev:.1f} mm)")
    sym = list(getattr(target, "symmetries", []) or [])
    if sym:
        shown = "; ".join(_rotation_text(R) for R in sym[:4]) + ("; ..." if len(sym) > 4 else "")
        lines.append(f"  symmetries: {len(sym)} besides identity ({shown}): poses a full view "
                     "cannot tell apart, resolved only by the port region or the track's history")
    else:
        lines.append("  symmetries: none found")
    return lines


# --------------------------------------------------------------------------- (c) observability
@dataclass
class MapRow:
    """The observability map at one distance to go (``range_m``: docking interface to port;
    ``sensor_range_m``: sensor to port)."""

    range_m: float
    sensor_range_m: float
    region: str
    port_bound_m: float
    attitude_bound_deg: float
    weak_axes: list[str]
    n_hits: int
    predicted_pl_m: float
    alert_limit_m: float
    planner_region: str
    planner_port_bound_m: float
    planner_attitude_bound_deg: float
    planner_weak_axes: list[str] = field(default_factory=list)

    @property
    def degraded(self) -> bool:
        return not (self.predicted_pl_m <= self.alert_limit_m)


def observability_map(cfg: Any, target: Any, ranges_m: tuple[float, ...] = MAP_RANGES_M) -> tuple[list[MapRow], str]:
    """Predicted single-frame bounds at the port along the nominal approach.

    Args:
        cfg: the mission config (sensor, pipeline strategies, integrity, chaser mount).
        target: the loaded target.
        ranges_m: docking-interface-to-port distances [m]; the sensor is placed where the
            chaser's mount puts it (``dynamics.chaser``), on the docking axis.

    Returns:
        The rows and the name of the strategy the mission uses (``range`` or ``observability``).
    """
    import numpy as np

    from perception.pipeline.integrity import alert_limit, integrity_factor
    from perception.pipeline.modes import ModeLogic
    from perception.pipeline.observability import ScanPlanner, predict_information
    from perception.pipeline import approach_pose
    from perception.estimation.registration import prepare_model
    from perception.sensing.sensors.tridar import TriDARSensor

    pc = cfg.pipeline
    sensor = TriDARSensor(cfg.sensor)
    target = target.model_view()  # what the estimator knows (a dense mesh's simplified copy)
    model = prepare_model(target, pc.icp.model_points)
    logic = ModeLogic(pc, sensor.transition_range_m)
    planner = ScanPlanner(target, sensor, model, pc.scan_plan, pc.icp.noise_floor_fraction)
    k = integrity_factor(pc.integrity.risk)
    planned = pc.scan_plan.mode == "observability"
    ch = cfg.dynamics.chaser
    # The port seen from the chaser's TriDAR: the docking axis is offset from the sensor (as in
    # the pipeline bench's V-bar replay).
    off = np.asarray(ch.dock_position_m, dtype=float) - np.asarray(ch.sensor_position_m, dtype=float)
    rows: list[MapRow] = []
    for r in ranges_m:
        T = approach_pose(cfg, target, float(r) + off[2], (off[0], off[1]))
        r_sensor = float(np.linalg.norm(T[:3, :3] @ target.T_target_port[:3, 3] + T[:3, 3]))
        default = logic.region_for_range(float(np.linalg.norm(T[:3, 3])))
        region = target.regions.get(default) or target.regions["whole"]
        base = predict_information(target, sensor, model, T, region, 0, pc.scan_plan.rays,
                                   pc.scan_plan, pc.icp.noise_floor_fraction)
        best = _planner_choice(planner, T, default, base)
        # The pipeline's planner steps in where the strategy's region leaves axes unobserved.
        used = best if planned and base.degenerate_axes else base
        rows.append(MapRow(
            range_m=float(r), sensor_range_m=r_sensor, region=used.region.name, port_bound_m=used.port_bound_m,
            attitude_bound_deg=math.degrees(used.attitude_bound_rad), weak_axes=list(used.degenerate_axes),
            n_hits=int(used.n_hits), predicted_pl_m=k * used.port_bound_m,
            alert_limit_m=alert_limit(r_sensor, pc.integrity.alert_limit_m, pc.integrity.alert_limit_range_m),
            planner_region=best.region.name, planner_port_bound_m=best.port_bound_m,
            planner_attitude_bound_deg=math.degrees(best.attitude_bound_rad),
            planner_weak_axes=list(best.degenerate_axes),
        ))
    return rows, ("observability" if planned else "range")


def _planner_choice(planner: Any, T: Any, default_name: str, base: Any) -> Any:
    """The prediction of the region the planner picks at ``T`` when asked to plan."""
    planner.reset()
    try:  # the planner plans when the last registration was weak
        _, pred = planner.choose(T, default_name, 0, 0.0, weak=True)
    except TypeError:  # a planner that plans on every call
        _, pred = planner.choose(T, default_name, 0, 0.0)
    return pred if pred is not None else base


def _mm(x: float) -> str:
    if not math.isfinite(x):
        return "inf"
    return f"{1e3 * x:.3g}" if x < 1e3 else ">1e6"


def _deg(x: float) -> str:
    return f"{x:.3g}" if math.isfinite(x) and x < 1e4 else ">1e4"


def map_table(rows: list[MapRow]) -> str:
    from agents.benchmarks.timing import format_table

    return format_table([{
        "to go [m]": f"{r.range_m:g}",
        "sensor range [m]": f"{r.sensor_range_m:.2f}",
        "region": r.region,
        "hits": r.n_hits,
        "port 1-sigma [mm]": _mm(r.port_bound_m),
        "att 1-sigma [deg]": _deg(r.attitude_bound_deg),
        "weak axes": ",".join(r.weak_axes) or "-",
        "pred. PL / AL [mm]": f"{_mm(r.predicted_pl_m)} / {_mm(r.alert_limit_m)}",
        "degraded": "yes" if r.degraded else "no",
        "planner region": r.planner_region,
        "planner port [mm]": _mm(r.planner_port_bound_m),
        "planner weak": ",".join(r.planner_weak_axes) or "-",
    } for r in rows])


def plot_map(path: Path, rows: list[MapRow], title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rng = np.array([r.range_m for r in rows])
    cap = 1e3  # unobserved directions carry ~1e6 variance: drawn at the top of the axis

    def clip(v: list[float]) -> np.ndarray:
        a = np.asarray(v, dtype=float)
        return np.where(np.isfinite(a), np.minimum(a, cap), cap)

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.5), dpi=110)
    a1.plot(rng, clip([1e3 * r.port_bound_m for r in rows]), "o-", label="mission strategy")
    a1.plot(rng, clip([1e3 * r.planner_port_bound_m for r in rows]), "s--", label="observability planner")
    a1.plot(rng, [1e3 * r.alert_limit_m for r in rows], "k:", label="alert limit")
    a1.plot(rng, clip([1e3 * r.predicted_pl_m for r in rows]), "^-", alpha=0.6, label="predicted PL (mission)")
    for r in rows:
        if r.weak_axes:
            a1.annotate(",".join(r.weak_axes), (r.range_m, min(1e3 * r.port_bound_m, cap)), fontsize=7,
                        rotation=30, xytext=(3, 3), textcoords="offset points", color="C3")
    for ax in (a1, a2):
        ax.axhline(cap, color="C3", lw=0.8, alpha=0.5)
        ax.text(0.02, 0.97, "top line: unobserved (variance ~1e6, drawn at the cap)", transform=ax.transAxes,
                fontsize=7, color="C3", va="top")
    a1.set_ylabel("port position [mm]")
    a2.plot(rng, clip([r.attitude_bound_deg for r in rows]), "o-", label="mission strategy")
    a2.plot(rng, clip([r.planner_attitude_bound_deg for r in rows]), "s--", label="observability planner")
    a2.set_ylabel("attitude 1-sigma [deg]")
    for ax in (a1, a2):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.invert_xaxis()
        ax.set_xlabel("docking interface to port [m]")
        ax.grid(True, which="both", alpha=0.2)
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------- (d) campaign
def degraded_by_range(records: list[Any]) -> list[tuple[tuple[float, float], int, float]]:
    """``((lo, hi), frames, degraded fraction)`` per range bin over the records' pose frames."""
    import numpy as np

    from agents.benchmarks.integrity import RANGE_BINS_M

    if not records:
        return []
    rng = np.concatenate([r.range_m for r in records])
    deg = np.concatenate([r.degraded for r in records]).astype(bool)
    out = []
    for lo, hi in RANGE_BINS_M:
        m = (rng >= lo) & (rng < hi)
        if m.any():
            out.append(((lo, hi), int(m.sum()), float(deg[m].mean())))
    return out


def _bin_text(b: tuple[float, float]) -> str:
    return f"{b[0]:g}-{b[1]:g} m" if math.isfinite(b[1]) else f"> {b[0]:g} m"


# --------------------------------------------------------------------------- (c') calibration
def accuracy_calibration(cfg: Any, target: Any) -> tuple[Any, list[str]]:
    """The correlated registration error of the mission's pipeline on ``target``
    (``TriDAR.accuracy_table``: what the pipeline publishes with
    ``integrity.accuracy_calibration``) and the ranges where it exceeds the protection level's
    allowance (the table is the shape's own error, without the time of flight's configured
    range bias, which the bound takes separately along the line of sight)."""
    from perception.pipeline import TriDAR

    table = TriDAR(cfg, target).accuracy_table
    ig = cfg.pipeline.integrity
    over = []
    for r, a, b in zip(table.range_m, table.across_m, table.along_m, strict=True):
        allow = max(ig.bias_m, ig.bias_rad * float(r))
        if (math.isfinite(a) and a > allow) or (math.isfinite(b) and b > allow):
            over.append(f"{r:.1f} m")
    return table, over


def calibration_table(table: Any, cfg: Any) -> str:
    """The calibration as a text table, beside the protection level's allowance per range."""
    from agents.benchmarks.timing import format_table

    ig = cfg.pipeline.integrity
    rows = []
    for i, r in enumerate(table.range_m):
        allow = max(ig.bias_m, ig.bias_rad * float(r))
        rows.append({
            "sensor-port range [m]": f"{r:.1f}",
            "along LOS [mm]": _or_dash(table.along_m[i], _mm),
            "across LOS [mm]": _or_dash(table.across_m[i], _mm),
            "attitude [deg]": _or_dash(math.degrees(table.attitude_rad[i]), _deg),
            "aspects (along/across/att)": "/".join(str(int(n)) for n in table.samples[i]),
            "PL allowance [mm]": _mm(allow),
        })
    return format_table(rows)


def _or_dash(x: float, fmt: Any) -> str:
    """``fmt(x)``, or "-" for a figure no aspect observed (NaN)."""
    return "-" if math.isnan(x) else str(fmt(x))


def calibration_csv(table: Any) -> str:
    lines = ["range_m,along_m,across_m,attitude_rad,n_along,n_across,n_attitude"]
    for i, r in enumerate(table.range_m):
        n = table.samples[i]
        lines.append(f"{r:.6g},{table.along_m[i]:.6g},{table.across_m[i]:.6g},{table.attitude_rad[i]:.6g},"
                     f"{int(n[0])},{int(n[1])},{int(n[2])}")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- (e) verdict
def verdict(rows: list[MapRow], campaign: dict[str, dict[str, Any]] | None,
            deg_bins: list[tuple[tuple[float, float], int, float]],
            over_allowance: list[str] | None = None) -> tuple[str, list[str]]:
    """READY / DEGRADED / NOT READY and the reasons (one line each)."""
    not_ready: list[str] = []
    degraded: list[str] = []
    if over_allowance:
        degraded.append("the model's correlated registration error exceeds the protection level's "
                        "allowance (integrity.bias_m / bias_rad) at " + ", ".join(over_allowance)
                        + ": raise it, or the bound may not cover this shape")
    close = [r for r in rows if r.range_m <= CLOSE_IN_M]
    if close and all(r.weak_axes and r.planner_weak_axes for r in close):
        not_ready.append("no candidate region observes all six axes inside "
                         f"{CLOSE_IN_M:g} m (weak: {','.join(sorted({a for r in close for a in r.planner_weak_axes}))})")
    weak = [r for r in rows if r.weak_axes]
    if weak:
        degraded.append("mission strategy leaves axes unobserved at "
                        + ", ".join(f"{r.range_m:g} m ({','.join(r.weak_axes)}, region {r.region})" for r in weak))
    pred = [r for r in rows if r.degraded]
    if pred:
        degraded.append("predicted single-frame PL above the alert limit at "
                        + ", ".join(f"{r.range_m:g} m" for r in pred))
    if campaign is not None:
        tr, pl = campaign["truth"], campaign["tridar"]
        if tr["docked_pct"] < 100.0:
            not_ready.append(f"the approach fails even on truth: {tr['terminations']} "
                             "(mission/controller, not navigation)")
        if pl["hmi"] > 0:
            not_ready.append(f"{pl['hmi']} hazardously misleading frames (valid pose, port error > PL; "
                             f"max valid port error {pl['max_err_valid_m']:.3f} m)")
        if pl["docked_pct"] < 50.0:
            not_ready.append(f"docks {pl['docked_pct']:.0f} % of runs on the pipeline ({pl['terminations']})")
        elif pl["docked_pct"] < 100.0:
            degraded.append(f"docks {pl['docked_pct']:.0f} % of runs on the pipeline ({pl['terminations']})")
        if pl["mi"] > pl["hmi"]:
            degraded.append(f"{pl['mi'] - pl['hmi']} degraded frames with port error > PL (flagged, not hazardous)")
        bad = [(b, f) for b, _, f in deg_bins if f > 0.0]
        if bad:
            degraded.append("pose published degraded (PL > AL: controller holds) at sensor-to-port range "
                            + ", ".join(f"{_bin_text(b)} ({100 * f:.2g} % of frames)" for b, f in bad))
    if not_ready:
        return "NOT READY", not_ready + degraded
    if degraded:
        return "DEGRADED", degraded
    return "READY", ["all six axes observed along the approach"
                     + ("; every run docked on truth and on the pipeline, no misleading frame"
                        if campaign is not None else "; closed loop not checked (--no-campaign)")]


# --------------------------------------------------------------------------- command
def run(args: argparse.Namespace) -> int:
    from agents.benchmarks.integrity import (
        TargetCase,
        display_row,
        file_case,
        fly,
        library_case,
        make_case_env,
        new_folder,
        plot_error_vs_pl,
        summarise,
        write_rows,
    )
    from agents.benchmarks.timing import format_table
    from perception.config import load_config
    from perception.estimation.pah import PAHDatabase

    if args.runs < 1:
        raise ValueError(f"--runs={args.runs}; expected >= 1")
    lines: list[str] = []

    def say(s: str = "") -> None:
        print(s, flush=True)
        lines.append(s)

    # (a) validation: a refusal propagates as one ValueError line (exit code 2 from the CLI).
    t0 = time.perf_counter()
    target, load_warnings = load_checked(args)
    t_load = time.perf_counter() - t0
    if not Path(args.mesh).suffix:
        case = library_case(args.mesh)
    elif args.port is not None:
        case = file_case(target.name, args.mesh, args.port, args.axis, args.scale)
    else:  # the env's loader places the same default port (and warns) when none is given
        case = TargetCase(target.name, {"target__name": str(args.mesh),
                                        **({"target__scale": args.scale} if args.scale else {})})
    cfg = load_config("final_approach", **case.overrides)

    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    # A new folder (an existing one gets a -2, -3... sibling), marked as a check-target report.
    out = new_folder(
        args.out if args.out is not None else Path("reports") / f"check-target-{target.name}-{stamp}",
        KIND,
    )
    say(f"check-target {args.mesh}: stock final_approach mission, report in {out}")
    say(f"(a) validation: loaded in {t_load:.1f} s")
    for w in load_warnings:
        say(f"  warning: {w}")
    for s in describe_target(target):
        say(s)

    # (b) PAH database
    t0 = time.perf_counter()
    db = PAHDatabase.build(target.model_view(), cfg.pipeline.pah)
    t_pah = time.perf_counter() - t0
    n_entries = next((len(getattr(db, a)) for a in ("entries", "keys", "views", "table")
                      if hasattr(db, a) and hasattr(getattr(db, a), "__len__")), None)
    say(f"(b) PAH database built in {t_pah:.1f} s" + (f" ({n_entries} entries)" if n_entries else ""))

    # (c) observability map
    t0 = time.perf_counter()
    rows, strategy = observability_map(cfg, target)
    say(f"(c) observability map along the nominal approach ({time.perf_counter() - t0:.1f} s): one "
        f"tracking frame's predicted 1-sigma bound at the port; mission strategy '{strategy}'; "
        f"predicted PL = {_pl_factor(cfg):.2f} x port bound (risk {cfg.pipeline.integrity.risk:g})")
    say(map_table(rows))
    _write_map_csv(out / "observability.csv", rows)
    plot_map(out / "observability.png", rows, f"{target.name}: predicted bounds along the approach")

    # (c') the correlated error calibrated on the model
    t0 = time.perf_counter()
    table, over = accuracy_calibration(cfg, target)
    say(f"(c') correlated registration error calibrated on the model ({time.perf_counter() - t0:.1f} s; "
        "1-sigma at the port over dispersed aspects, white noise removed, beside the protection "
        "level's allowance)")
    say(calibration_table(table, cfg))
    (out / "accuracy_calibration.csv").write_text(calibration_csv(table))

    # (d) closed-loop campaign
    campaign: dict[str, dict[str, Any]] | None = None
    deg_bins: list = []
    if not args.no_campaign:
        from tqdm import tqdm

        seeds = [args.seeds_offset + i for i in range(args.runs)]
        say(f"(d) closed loop: glideslope, {args.runs} runs each on truth and on the full pipeline "
            f"(reset seeds {seeds[0]}..{seeds[-1]})")
        records: dict[str, list[Any]] = {}
        per_run: list[dict[str, Any]] = []
        bar = tqdm(total=2 * len(seeds), desc="check-target", unit="run", mininterval=1.0)
        for perception in ("truth", "tridar"):
            env = make_case_env(case, perception)
            recs = []
            try:
                for s in seeds:
                    bar.set_postfix_str(f"{perception} seed {s}")
                    rec = fly(env, s, max_steps=args.max_steps)
                    rec.label = f"{target.name} {perception}"
                    recs.append(rec)
                    per_run.append({"perception": perception, **rec.summary()})
                    bar.update()
            finally:
                env.close()
            records[perception] = recs
        bar.close()
        campaign = {p: summarise(f"{target.name} {p}", recs) for p, recs in records.items()}
        say(format_table([display_row(r) for r in campaign.values()]))
        deg_bins = degraded_by_range(records["tridar"])
        if deg_bins:
            say("  pipeline pose frames by sensor-to-port range: " + "; ".join(
                f"{_bin_text(b)} {n} frames, {100 * f:.2g} % degraded" for b, n, f in deg_bins))
        write_rows(out, list(campaign.values()), {"mesh": str(args.mesh), "overrides": case.overrides,
                                                  "seeds": seeds, "max_steps": args.max_steps})
        import csv

        with (out / "campaign_runs.csv").open("x", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(per_run[0].keys()))
            w.writeheader()
            w.writerows(per_run)
        plot_error_vs_pl(out / "error_vs_pl.png", [("tridar", records["tridar"])])

    # (e) verdict
    word, reasons = verdict(rows, campaign, deg_bins, over)
    say("")
    say(f"VERDICT: {word}")
    for r in reasons:
        say(f"  - {r}")
    with (out / "report.txt").open("x") as f:
        f.write("\n".join(lines) + "\n")
    print(f"wrote {out}")
    return 0


def _pl_factor(cfg: Any) -> float:
    from perception.pipeline.integrity import integrity_factor

    return integrity_factor(cfg.pipeline.integrity.risk)


def _write_map_csv(path: Path, rows: list[MapRow]) -> None:
    import csv
    from dataclasses import asdict

    with path.open("x", newline="") as f:
        w = csv.writer(f)
        keys = list(asdict(rows[0]).keys()) + ["degraded"]
        w.writerow(keys)
        for r in rows:
            d = asdict(r)
            w.writerow([",".join(v) if isinstance(v, list) else v for v in d.values()] + [r.degraded])
