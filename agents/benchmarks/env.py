"""Environment throughput: steps/s with ``perception="truth"`` and ``"tridar"``, single and vector.

Uses ``gymnasium.utils.performance.benchmark_step`` (random actions, auto-reset) on each id; the
peer row is the same env with truth perception, so the ratio shows what the TriDAR pipeline (or,
with ``--perceptions truth flash``, the flash pipeline) costs.
Vector rows use ``benchmark_vector_step`` (environment steps per second, all environments
together): ``async`` processes for both perceptions, and for truth the batched
:class:`~tridar_env.vector.TruthVectorEnv` (``vectorization_mode="vector_entry_point"``).
Goals: >= 20,000 steps/s with truth, >= 200 steps/s with the full pipeline on one core.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
from gymnasium.utils.performance import benchmark_step, benchmark_vector_step

import tridar_env  # registers the ids
from agents.benchmarks.timing import format_table


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=3.0, help="measuring time per row [s]")
    p.add_argument("--ids", nargs="*", default=list(tridar_env.ENV_IDS), help="env ids")
    p.add_argument("--vector", type=int, default=2, help="envs in the async vector rows (0: skip)")
    p.add_argument("--batched", type=int, default=64, help="envs in the batched truth row (0: skip)")
    p.add_argument("--repeats", type=int, default=3, help="measurements per row (median, p90)")
    p.add_argument("--perceptions", nargs="*", default=["truth", "tridar"],
                   choices=["truth", "truth+noise", "tridar", "flash"],
                   help="perception modes (truth first: the others' ratio is to it)")


def _measure(fn, repeats: int) -> tuple[float, float]:
    rates = [fn() for _ in range(repeats)]
    # Steps/s: the median and the 10th percentile (the slow tail, "p90" of the step time).
    return float(np.median(rates)), float(np.percentile(rates, 10))


def _vector_row(venv, env_id: str, perception: str, envs: str, base: float | None, secs: int,
                repeats: int) -> dict:
    """One table row for a vector env (then closed); ``benchmark_vector_step`` already counts
    every environment's steps."""
    med, slow = _measure(lambda: benchmark_vector_step(venv, target_duration=secs, seed=0), repeats)
    venv.close()
    return {
        "id": env_id, "perception": perception, "envs": envs, "steps_per_s_median": med,
        "steps_per_s_p10": slow, "ratio_to_truth": med / base if base else 1.0,
    }


def run(args: argparse.Namespace) -> int:
    rows = []
    secs = max(round(args.seconds), 1)
    for env_id in args.ids:
        base = None
        for perception in args.perceptions:
            env = gym.make(env_id, perception=perception)
            med, slow = _measure(lambda env=env: benchmark_step(env, target_duration=secs, seed=0), args.repeats)
            base = med if perception == "truth" else base
            rows.append({
                "id": env_id, "perception": perception, "envs": 1, "steps_per_s_median": med,
                "steps_per_s_p10": slow, "ratio_to_truth": med / base if base else 1.0,
            })
            env.close()
            if args.vector > 1:
                venv = gym.make_vec(env_id, num_envs=args.vector, vectorization_mode="async",
                                    vector_kwargs={"context": "spawn"}, perception=perception)
                rows.append(_vector_row(venv, env_id, perception, f"{args.vector} async", base, secs, args.repeats))
            if perception == "truth" and args.batched > 0:
                try:
                    benv = gym.make_vec(env_id, num_envs=args.batched, vectorization_mode="vector_entry_point",
                                        perception="truth")
                except ValueError as exc:  # a configuration the batched env does not cover
                    print(f"{env_id}: no batched row ({exc})")
                    continue
                rows.append(_vector_row(benv, env_id, perception, f"{args.batched} batched", base, secs, args.repeats))
    print(format_table(rows))
    print("goals: >= 20,000 steps/s truth, >= 200 steps/s tridar (one core)")
    return 0
