"""Soak: a million truth steps and 100,000 TriDAR steps; resident memory and steps/s over time.

Steps the truth env (the batched :class:`~tridar_env.vector.TruthVectorEnv`, the fastest public
path; a single ``perception="truth"`` env for a configuration it does not batch) for
``--truth-steps`` environment steps, then the full TriDAR pipeline (``gym.make(...,
perception="tridar")``) for ``--tridar-steps`` steps, both with seeded random actions and a reset
at every episode end. At ``--checkpoints`` evenly spaced points of each phase it samples the
resident set size (``VmRSS`` of ``/proc/self/status``, else psutil) after a garbage collection,
and the steps/s since the previous checkpoint. The first checkpoint closes the warm-up (imports,
caches, the PAH database, allocator pools): growth is measured against it. Verdict: every phase's
RSS grows by less than 5 % after warm-up (exit 1 otherwise).
"""

from __future__ import annotations

import argparse
import gc
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym

import tridar_env  # registers the ids
from agents.benchmarks.timing import format_table

#: Largest RSS growth after warm-up that passes [%].
MAX_GROWTH_PCT = 5.0


@dataclass(frozen=True)
class Checkpoint:
    """One sample of a soak phase: cumulative steps, resident memory, throughput since the last."""

    phase: str
    steps: int
    rss_mib: float
    growth_pct: float  # vs the phase's first checkpoint (the end of warm-up) [%]
    steps_per_s: float


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--truth-steps", type=_count, default=1_000_000,
                   help="environment steps on truth perception (default 1e6)")
    p.add_argument("--tridar-steps", type=_count, default=100_000,
                   help="environment steps through the TriDAR pipeline (default 1e5)")
    p.add_argument("--env-id", default="TriDAR/FinalApproach-v0", choices=list(tridar_env.ENV_IDS),
                   help="Gymnasium id (default TriDAR/FinalApproach-v0)")
    p.add_argument("--envs", type=_count, default=64,
                   help="environments in the batched truth env (default 64)")
    p.add_argument("--checkpoints", type=_count, default=10,
                   help="samples per phase, the first closing the warm-up (default 10)")
    p.add_argument("--seed", type=int, default=0, help="reset and action seed (default 0)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _count(text: str) -> int:
    """A positive count; ``1e6`` is accepted."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value >= 1 and value == int(value)):
        raise argparse.ArgumentTypeError(f"{text!r}; expected a whole number >= 1")
    return int(value)


def rss_mib() -> float:
    """Resident set size of this process [MiB] (``/proc/self/status``, else psutil)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    import psutil  # not on Linux: the optional dependency

    return psutil.Process().memory_info().rss / 2**20


def soak(
    phase: str,
    step: Callable[[], int],
    total: int,
    checkpoints: int,
    progress: bool = False,
    memory: Callable[[], float] = rss_mib,
) -> list[Checkpoint]:
    """Call ``step`` (which takes some steps and returns how many) until ``total`` steps.

    Args:
        phase: label of the rows.
        step: one call of the loop; returns the number of environment steps it took (>= 1).
        total: environment steps to take.
        checkpoints: samples, evenly spaced in steps; the first is the growth baseline.
        progress: a tqdm bar over the steps.
        memory: the memory probe [MiB] (tests pass a scripted one).

    Returns:
        One :class:`Checkpoint` per sample (fewer if ``total`` is smaller than ``checkpoints``).
    """
    n_cp = max(1, min(int(checkpoints), int(total)))
    marks = [math.ceil(total * (k + 1) / n_cp) for k in range(n_cp)]
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=total, desc=phase, unit="step", unit_scale=True, leave=False)
    rows: list[Checkpoint] = []
    done, base = 0, None
    t_last, done_last = time.perf_counter(), 0
    try:
        for mark in marks:
            while done < mark:
                k = step()
                done += k
                if bar is not None:
                    bar.update(k)
            now = time.perf_counter()
            rate = (done - done_last) / max(now - t_last, 1e-9)
            gc.collect()
            rss = float(memory())
            base = rss if base is None else base
            rows.append(Checkpoint(phase, done, rss, growth_pct(rss, base), rate))
            t_last, done_last = time.perf_counter(), done  # the collection is not stepping time
    finally:
        if bar is not None:
            bar.close()
    return rows


def growth_pct(rss: float, base: float) -> float:
    """Growth of ``rss`` over ``base`` [%]."""
    return 100.0 * (rss - base) / base


def _truth_phase(args: argparse.Namespace) -> list[Checkpoint]:
    try:
        env = gym.make_vec(args.env_id, num_envs=args.envs, vectorization_mode="vector_entry_point",
                           perception="truth")
        label = f"truth ({args.envs} batched)"
    except ValueError:  # a configuration the batched env does not cover
        env, label = None, "truth (single)"
    if env is not None:
        env.reset(seed=args.seed)
        env.action_space.seed(args.seed)
        n = args.envs

        def step() -> int:
            env.step(env.action_space.sample())  # finished envs reset on the next step
            return n
    else:
        env = gym.make(args.env_id, perception="truth")
        step = _single_stepper(env, args.seed)
    try:
        return soak(label, step, args.truth_steps, args.checkpoints, not args.no_progress)
    finally:
        env.close()


def _single_stepper(env: gym.Env, seed: int) -> Callable[[], int]:
    env.reset(seed=seed)
    env.action_space.seed(seed)

    def step() -> int:
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset()
        return 1

    return step


def _tridar_phase(args: argparse.Namespace) -> list[Checkpoint]:
    env = gym.make(args.env_id, perception="tridar")
    try:
        step = _single_stepper(env, args.seed)
        return soak("tridar", step, args.tridar_steps, args.checkpoints, not args.no_progress)
    finally:
        env.close()


def verdict(rows: list[Checkpoint], max_growth_pct: float = MAX_GROWTH_PCT) -> tuple[bool, str]:
    """Pass when every phase's largest growth after warm-up stays below ``max_growth_pct``."""
    parts, ok = [], True
    for phase in dict.fromkeys(r.phase for r in rows):
        worst = max(r.growth_pct for r in rows if r.phase == phase)
        ok &= worst < max_growth_pct
        parts.append(f"{phase} {worst:+.1f} %")
    word = "PASS" if ok else "FAIL"
    return ok, (f"verdict: {word}: largest RSS growth after warm-up {', '.join(parts)} "
                f"(limit {max_growth_pct:g} %)")


def run(args: argparse.Namespace) -> int:
    rows = _truth_phase(args)
    gc.collect()
    rows += _tridar_phase(args)
    print(format_table([
        {"phase": r.phase, "steps": r.steps, "RSS MiB": round(r.rss_mib, 1),
         "growth %": round(r.growth_pct, 2), "steps/s": round(r.steps_per_s)}
        for r in rows
    ], floatfmt=".6g"))
    ok, line = verdict(rows)
    print(line)
    return 0 if ok else 1

