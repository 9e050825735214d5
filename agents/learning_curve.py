"""The learning curve of a training run: how its episodes end, against steps and wall time.

The return alone does not say whether a policy docks or only survives; how the episodes end does.
:class:`LearningCurve` (a stable-baselines3 callback) keeps the last ``window`` finished episodes
(cause, return, length), logs the fractions of each cause to TensorBoard (``outcome/<cause>``)
and, when given a path, appends one row per rollout to a CSV file (:data:`COLUMNS`): steps, wall
seconds since training started, episodes finished so far, the window's mean return and length and
its fraction of each cause. :func:`read_learning_curve` reads it back and :func:`plot_learning_curve`
draws it (docked / collision / truncated fractions and the mean return against steps, with the
wall time on a second axis).

Example:
    >>> from agents.learning_curve import COLUMNS
    >>> COLUMNS[:3]
    ('timesteps', 'wall_s', 'episodes')
"""

from __future__ import annotations

import csv
import math
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from tridar_env.env import CAUSES

__all__ = ["COLUMNS", "LearningCurve", "plot_learning_curve", "read_learning_curve"]

OUTCOMES = (*CAUSES, "truncated")
COLUMNS = ("timesteps", "wall_s", "episodes", "return_mean", "length_mean", *OUTCOMES)
_COUNTS = ("timesteps", "episodes")


class LearningCurve(BaseCallback):  # type: ignore[misc]
    """How the last ``window`` training episodes ended, per rollout (see the module docstring).

    Args:
        path: CSV file to append a row to at the end of every rollout (None: TensorBoard only).
            The file is created with its header by the first row; an existing file is refused
            (the caller clears what an earlier run of its own wrote).
        window: number of most recent episodes the fractions and means are taken over.
    """

    def __init__(self, path: str | Path | None = None, window: int = 100) -> None:
        super().__init__()
        if int(window) < 1:
            raise ValueError(f"window={window!r}; expected a positive number of episodes")
        self.path = None if path is None else Path(path)
        if self.path is not None and self.path.exists():
            raise ValueError(f"{self.path} exists (an earlier run's learning curve); pass --force to "
                             "replace that run or choose another --out")
        self.window = int(window)
        self.causes: deque[str] = deque(maxlen=self.window)
        self.returns: deque[float] = deque(maxlen=self.window)
        self.lengths: deque[int] = deque(maxlen=self.window)
        self.episodes = 0
        self._t0 = time.perf_counter()

    def _on_training_start(self) -> None:
        self._t0 = time.perf_counter()

    def _on_step(self) -> bool:
        for done, info in zip(self.locals["dones"], self.locals["infos"]):
            if not done:
                continue
            self.episodes += 1
            self.causes.append(info.get("termination") or "truncated")
            ep = info.get("episode")
            if ep is not None:
                self.returns.append(float(ep["r"]))
                self.lengths.append(int(ep["l"]))
        if self.causes:
            for cause in OUTCOMES:
                self.logger.record(f"outcome/{cause}", self.causes.count(cause) / len(self.causes))
        return True

    def row(self) -> dict[str, float]:
        """The current row of the curve (:data:`COLUMNS`); NaN fractions before any episode ended."""
        n = len(self.causes)
        out: dict[str, float] = {
            "timesteps": float(self.num_timesteps),
            "wall_s": time.perf_counter() - self._t0,
            "episodes": float(self.episodes),
            "return_mean": float(np.mean(self.returns)) if self.returns else math.nan,
            "length_mean": float(np.mean(self.lengths)) if self.lengths else math.nan,
        }
        for cause in OUTCOMES:
            out[cause] = self.causes.count(cause) / n if n else math.nan
        return out

    def _on_rollout_end(self) -> None:
        if self.path is None:
            return
        new = not self.path.exists()
        with self.path.open("a", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=COLUMNS, lineterminator="\n")
            if new:
                writer.writeheader()
            r = self.row()
            writer.writerow({k: (f"{int(r[k])}" if k in _COUNTS else
                                 f"{r[k]:.6g}" if not math.isnan(r[k]) else "nan") for k in COLUMNS})


def read_learning_curve(path: str | Path) -> dict[str, np.ndarray]:
    """The columns of a learning-curve CSV as float arrays (:data:`COLUMNS`).

    Raises:
        ValueError: the file's header is not :data:`COLUMNS`, or a value is not a number.
    """
    p = Path(path)
    with p.open(newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None or tuple(header) != COLUMNS:
            raise ValueError(f"{p}: header {header!r}; expected the columns {list(COLUMNS)}")
        rows = []
        for i, line in enumerate(reader, start=2):
            if len(line) != len(COLUMNS):
                raise ValueError(f"{p}: line {i} has {len(line)} values; expected {len(COLUMNS)}")
            try:
                rows.append([float(v) for v in line])
            except ValueError:
                raise ValueError(f"{p}: line {i} holds a value that is not a number: {line!r}") from None
    arr = np.asarray(rows, dtype=np.float64).reshape(-1, len(COLUMNS))
    return {name: arr[:, k] for k, name in enumerate(COLUMNS)}


def plot_learning_curve(csv_path: str | Path, png_path: str | Path, title: str = "",
                        validation: str | Path | None = None) -> Path:
    """Draw the curve of ``csv_path`` into ``png_path``: outcome fractions and mean return
    against training steps, the wall time on the top axis, and the docked fraction of each
    validation (``validation.csv`` of :mod:`agents.validation`) when given. Returns ``png_path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = read_learning_curve(csv_path)
    steps = c["timesteps"] / 1e6
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 6.5), dpi=110, sharex=True)
    for cause, style in (("docked", "g-"), ("collision", "r-"), ("truncated", "b--"),
                         ("corridor_exit", "m:")):
        a1.plot(steps, 100.0 * c[cause], style, label=cause)
    if validation is not None:
        v = np.genfromtxt(validation, delimiter=",", names=True, ndmin=1)
        if v.size:
            a1.plot(v["timesteps"] / 1e6, 100.0 * v["docked"] / v["episodes"], "ko", ms=4,
                    label="docked, validation")
    a1.set_ylabel("recent training episodes [%]")
    a1.set_ylim(-2, 102)
    a1.grid(alpha=0.3)
    a1.legend(loc="center right", fontsize=8)
    a2.plot(steps, c["return_mean"], "k-")
    a2.set_ylabel("mean episode return")
    a2.set_xlabel("training steps [millions]")
    a2.grid(alpha=0.3)
    if len(steps) > 1 and steps[-1] > steps[0]:
        top = a1.secondary_xaxis(
            "top", functions=(lambda s: np.interp(s, steps, c["wall_s"] / 60.0),
                              lambda m: np.interp(m, c["wall_s"] / 60.0, steps)))
        top.set_xlabel("wall time [min]")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out = Path(png_path)
    fig.savefig(out)
    plt.close(fig)
    return out
