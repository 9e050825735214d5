"""``tridar-env demo`` and ``tridar-env run MISSION``: fly one episode, summarise it, write a report.

``demo`` is the README's first command: with no arguments it flies ``TriDAR/FinalApproach-v0``
with the glideslope controller on the perception mode of the mission file (the full TriDAR
pipeline), shows a progress bar, prints a one-screen summary and writes ``reports/demo-<time>/``
(:mod:`agents.report`). ``run`` is the general form for any mission YAML (or bare mission name)
and controller. Both exit 0 when the chaser docked, 1 otherwise.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import Any

import yaml

from agents.cli import command

DEMO_ENV_ID = "TriDAR/FinalApproach-v0"
CONTROLLERS = "glideslope | lqr | sync | fly_around | sb3:<model.zip> | module:Class"


def _common(p: argparse.ArgumentParser, controller_default: str, out_default: str) -> None:
    p.add_argument("--controller", default=None,
                   help=f"{CONTROLLERS} (default: {controller_default})")
    p.add_argument("--perception", choices=["tridar", "flash", "truth", "truth+noise"], default=None,
                   help="state-vector source (default: env.perception of the mission config)")
    p.add_argument("--seed", type=int, default=0, help="reset seed (default 0)")
    p.add_argument("--out", type=Path, default=None,
                   help=f"report folder (default {out_default}); a new or empty folder, or an "
                        "earlier report's")
    p.add_argument("--render-every", type=int, default=40, metavar="N",
                   help="render a video frame every N steps (default 40; 0: no video)")
    p.add_argument("--no-video", action="store_true", help="skip rendering and the video")
    p.add_argument("--fps", type=int, default=8, help="video frame rate (default 8)")
    p.add_argument("--max-steps", type=int, default=None, help="cap on the number of steps")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="config override, nested with '.' or '__' (env.initial.range_m=20); "
                        "repeatable; VALUE is parsed as YAML")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--record", type=Path, default=None, metavar="FILE.mcap",
                   help="record the run to MCAP (ROS 2 messages; tridar-env replay / view read it)")
    p.add_argument("--force", action="store_true", help="replace an existing --record file")
    p.add_argument("--view", action="store_true",
                   help="open the rerun 3D viewer on the run when it ends (the 'view' extra)")


@command("demo", "fly the final approach with the glideslope controller and write a report folder")
def add_demo(p: argparse.ArgumentParser) -> None:
    p.add_argument("--env-id", default=DEMO_ENV_ID, help=f"Gymnasium id (default {DEMO_ENV_ID})")
    _common(p, "glideslope", "reports/demo-<time>")
    p.set_defaults(handler=run_demo, controller_default="glideslope")


@command("run", "fly any mission YAML with a controller and write a report folder")
def add_run(p: argparse.ArgumentParser) -> None:
    p.add_argument("mission", help="mission YAML file or a name in configs/missions")
    _common(p, "fly_around for a fly-around task, sync for a 6-DOF chaser, else glideslope",
            "reports/run-<mission>-<time>")
    p.set_defaults(handler=run_mission, controller_default=None)


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["a.b=1", "c=x"]`` -> ``{"a__b": 1, "c": "x"}`` (values parsed as YAML)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set {item!r}; expected KEY=VALUE")
        out[key.strip().replace(".", "__")] = yaml.safe_load(value)
    return out


def run_demo(args: argparse.Namespace) -> int:
    import gymnasium as gym

    import tridar_env  # noqa: F401  (registers the ids)

    overrides = parse_overrides(args.overrides)
    if args.env_id not in gym.registry:
        raise ValueError(f"--env-id {args.env_id!r} is not registered; expected one of "
                         f"{', '.join(k for k in gym.registry if k.startswith('TriDAR/'))}")

    def make(render_mode: str | None) -> gym.Env:
        return gym.make(args.env_id, perception=args.perception, render_mode=render_mode,
                        config=overrides or None)

    return _fly(args, make, args.env_id, "demo")


def run_mission(args: argparse.Namespace) -> int:
    from gymnasium.wrappers import TimeLimit

    from tridar_env.env import DockingEnv

    overrides = parse_overrides(args.overrides)

    def make(render_mode: str | None) -> Any:
        env = DockingEnv(args.mission, perception=args.perception, render_mode=render_mode,
                         **overrides)
        return TimeLimit(env, env.cfg.env.max_episode_steps)

    return _fly(args, make, str(args.mission), f"run-{Path(args.mission).stem}")


def _fly(args: argparse.Namespace, make: Any, env_name: str, prefix: str) -> int:
    from tqdm import tqdm

    from agents.controllers import make_controller
    from agents.outputs import check_folder
    from agents.report import KIND as REPORT_KIND
    from agents.report import fly, format_summary, summary_dict, write_report

    render_every = 0 if args.no_video else args.render_every
    if render_every < 0:
        raise ValueError(f"--render-every={render_every}; expected >= 0")
    # A time-stamped default folder is always new: never written over, even by a demo started
    # in the same second. The folder is checked before anything is built.
    stamped = args.out is None
    out = args.out or Path("reports") / f"{prefix}-{time.strftime('%Y%m%d-%H%M%S')}"
    check_folder(out, REPORT_KIND, new=stamped)
    mcap_path = _record_path(args)
    try:
        env = make("rgb_array" if render_every else None)
    except ImportError as exc:
        raise ValueError(
            f"cannot build the environment ({exc}); the full TriDAR pipeline may not be installed "
            "yet: try --perception truth"
        ) from None
    if mcap_path is not None:
        from tridar_env.recording import RecordMCAP

        env = RecordMCAP(env, mcap_path, force=args.force or args.record is None, label=env_name)
    cfg = env.unwrapped.cfg
    name = args.controller or args.controller_default
    if name is None:
        name = ("fly_around" if cfg.env.task == "fly_around"
                else "sync" if cfg.dynamics.chaser.attitude == "controlled" else "glideslope")
    controller = make_controller(name, cfg)
    total = args.max_steps or cfg.env.max_episode_steps
    bar = tqdm(total=total, unit="step", disable=args.no_progress, dynamic_ncols=True,
               desc=f"{env_name} [{cfg.env.perception}]")
    try:
        record = fly(env, controller, args.seed, env_name=env_name, controller=name,
                     render_every=render_every, max_steps=args.max_steps,
                     on_step=lambda i: bar.update(1))
    finally:
        bar.total = bar.n  # the episode ended before the step limit
        bar.refresh()
        bar.close()
        env.close()
    write_report(record, out, video=bool(render_every), fps=args.fps, new=stamped)
    print(format_summary(summary_dict(record), out))
    if args.record is not None:
        print(f"recording: {args.record} (tridar-env view / tridar-env replay)")
    if args.view and mcap_path is not None:
        from agents.viewer import view

        try:
            view(mcap_path)
        finally:
            if args.record is None:
                mcap_path.unlink(missing_ok=True)
    return 0 if record.result.docked else 1


def _record_path(args: argparse.Namespace) -> Path | None:
    """Where the run is recorded: ``--record``, or for ``--view`` alone a temporary file."""
    if args.view:
        from agents.viewer import require_window

        require_window()  # a window can open: checked before the run rather than after it
    if args.record is not None:
        from tridar_env.mcap_log import refuse_existing

        return refuse_existing(args.record, args.force)
    if args.view:
        import tempfile

        return Path(tempfile.gettempdir()) / f"tridar-view-{os.getpid()}-{time.time_ns()}.mcap"
    return None
