"""``tridar-env envs``: list the Gymnasium ids, one line each."""

from __future__ import annotations

import argparse
import json

from agents.cli import command


@command("envs", "list the Gymnasium ids with their missions, one line each")
def add(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from perception.config import load_config
    from tridar_env.registration import ENV_IDS

    rows = []
    for env_id, mission in ENV_IDS.items():
        cfg = load_config(mission)
        e = cfg.env
        rows.append({
            "id": env_id, "mission": mission, "task": e.task, "target": cfg.target.name,
            "start_range_m": e.initial.range_m, "frame_period_s": e.frame_period_s,
            "max_episode_steps": e.max_episode_steps, "steps_lengthen": e.decision_schedule is not None,
            "description": cfg.description,
        })
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    head = f"{'id':<26} {'mission':<16} {'task':<11} {'target':<9} {'start':>8} {'steps':>6}  description"
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['id']:<26} {r['mission']:<16} {r['task']:<11} {r['target']:<9} "
              f"{r['start_range_m']:>6.0f} m {r['max_episode_steps']:>6}  {r['description']}")
    return 0
