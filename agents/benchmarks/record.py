"""Recording overhead: env steps/s with the TriDAR pipeline, with and without ``RecordMCAP``.

Both rows fly the same scripted episode (glideslope controller, same seed, same number of steps):
recording does not change the simulation, so the two do bitwise the same work but the recording,
which random actions (``bench env``) would not guarantee, since a step in search costs many
tracking steps. Plain and recorded runs alternate, and the time is this process's CPU time, so a
machine shared with other jobs slows neither row more than the other. The peer row is the plain
env. Also prints the recording's size per simulated second. Goal: recording costs <= 15 % of the
tridar steps/s.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

import tridar_env  # noqa: F401  (registers the ids)
from agents.benchmarks.timing import format_table


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--id", default="TriDAR/FinalApproach-v0", help="env id")
    p.add_argument("--perception", default="tridar", choices=["tridar", "flash", "truth"])
    p.add_argument("--steps", type=int, default=200, help="steps of the scripted episode")
    p.add_argument("--repeats", type=int, default=5, help="runs per row (median, p90)")
    p.add_argument("--controller", default="glideslope", help="controller flying the episode")
    p.add_argument("--compression", default="lz4", choices=["lz4", "zstd", "none"],
                   help="MCAP chunk compression of the recorded rows")


def _fly(env: gym.Env, controller, steps: int) -> tuple[float, int, float]:
    """CPU seconds, steps flown and simulated seconds of one episode from reset(seed=0)."""
    reset = getattr(controller, "reset", None)
    if reset is not None:
        reset()
    obs, _ = env.reset(seed=0)
    t0 = time.process_time()
    n = 0
    for n in range(1, steps + 1):  # n: the steps flown
        obs, _, term, trunc, info = env.step(controller(obs))
        if term or trunc:
            break
    return time.process_time() - t0, n, float(info["t"])


def run(args: argparse.Namespace) -> int:
    from agents.controllers import make_controller
    from tridar_env.recording import RecordMCAP

    plain = gym.make(args.id, perception=args.perception)
    ctrl = make_controller(args.controller, plain.unwrapped.cfg)
    rates: dict[str, list[float]] = {"off": [], "on": []}
    sizes, own, sim = [], [], 0.0
    with tempfile.TemporaryDirectory(prefix="tridar-bench-record-") as tmp:
        _fly(plain, ctrl, 5)  # warm-up: PAH database, caches
        for i in range(args.repeats):
            cpu, n, _ = _fly(plain, ctrl, args.steps)
            rates["off"].append(n / cpu)
            path = Path(tmp) / f"run{i}.mcap"
            rec = RecordMCAP(gym.make(args.id, perception=args.perception), path, label="bench",
                             compression=args.compression)
            cpu, n, sim = _fly(rec, ctrl, args.steps)
            t0 = time.process_time()
            rec.close()  # the last chunk's compression is part of the cost
            cpu += time.process_time() - t0
            rates["on"].append(n / cpu)
            own.append(rec.log.busy_s / n)
            sizes.append(path.stat().st_size)
    plain.close()
    base = float(np.median(rates["off"]))
    rows = []
    for key, label in (("off", "no recording"), ("on", f"RecordMCAP ({args.compression})")):
        r = np.asarray(rates[key])
        med, slow = float(np.median(r)), float(np.percentile(r, 10))
        rows.append({"id": args.id, "perception": args.perception, "recording": label,
                     "steps_per_s_median": med, "steps_per_s_p10": slow,
                     "step_ms_median": 1e3 / med, "step_ms_p90": 1e3 / slow, "ratio_to_plain": med / base})
    print(format_table(rows))
    size = float(np.median(sizes))
    # Each recorded run against the plain run just before it (the same load on the machine).
    paired = 1.0 - np.asarray(rates["on"]) / np.asarray(rates["off"])
    own_ms = 1e3 * np.asarray(own)
    print(f"the recorder's own time per step (timed inside it): median {float(np.median(own_ms)):.2f} ms, "
          f"p90 {float(np.percentile(own_ms, 90)):.2f} ms = {100.0 * float(np.median(own_ms)) * base / 1e3:.1f} % "
          "of a plain step")
    print(f"overhead per pair of runs: median {100.0 * float(np.median(paired)):.1f} %, p90 "
          f"{100.0 * float(np.percentile(paired, 90)):.1f} %")
    print(f"overhead: {100.0 * (1.0 - rows[1]['steps_per_s_median'] / base):.1f} % of the plain steps/s "
          f"(goal <= 15 %); {args.steps} steps = {sim:.0f} simulated s recorded in {size / 1e6:.1f} MB "
          f"({size / max(sim, 1e-9) / 1e3:.0f} kB per simulated s); CPU time of this process")
    return 0
