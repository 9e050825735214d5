"""``tridar-env targets``: list the target library."""

from __future__ import annotations

import argparse
import json

from agents.cli import command


@command("targets", "list the target library with envelopes, face counts and ports")
def add(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from perception.targets import LIBRARY, load_target

    rows = [load_target(name).summary() for name in LIBRARY]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    head = (
        f"{'name':<9} {'envelope x*y*z [m]':<22} {'faces':>6} {'mass [kg]':>10}  "
        f"{'port [m]':<24} {'axis':<12} description"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        ext = " x ".join(f"{v:.2f}" for v in r["extents_m"])
        port = "(" + ", ".join(f"{v:+.2f}" for v in r["port_m"]) + ")"
        axis = "(" + ",".join(f"{v:+.0f}" for v in r["port_axis"]) + ")"
        print(
            f"{r['name']:<9} {ext:<22} {r['faces']:>6} {r['mass_kg']:>10.0f}  {port:<24} "
            f"{axis:<12} {r['description']}"
        )
    return 0
