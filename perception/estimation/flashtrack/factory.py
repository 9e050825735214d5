"""``make_flash_tracker(kind, target)``: the flash trackers by name (the rows of bench seed003)."""

from __future__ import annotations

from typing import Any

import numpy as np

from perception.config import FlashLidarConfig, ICPConfig
from perception.estimation.flashtrack.base import FlashTracker, flash_range_sigma
from perception.estimation.flashtrack.icp import IcpFlashTracker
from perception.estimation.flashtrack.outline import OutlineFlashTracker
from perception.estimation.flashtrack.seed003 import Seed003Tracker
from perception.estimation.linetrack import seed003_icp_config
from perception.targets import TargetModel

__all__ = ["BEST_FLASH_TRACKER", "FLASH_TRACKER_KINDS", "make_flash_tracker"]

#: Kinds of :func:`make_flash_tracker`, from the seed's baseline to the project's best.
FLASH_TRACKER_KINDS: tuple[str, ...] = (
    "icp",
    "seed003",
    "p2plane",
    "seed003+p2plane",
    "p2plane+cv+rays",
    "p2plane+cv+outline",
    "p2plane+ekf+outline",
)

#: The most accurate kind (bench seed003: max 0.1 deg / 5 mm over experiments 1-2, ~10-20 ms).
BEST_FLASH_TRACKER = "p2plane+ekf+outline"


def make_flash_tracker(
    kind: str,
    target: TargetModel,
    *,
    flash: FlashLidarConfig | None = None,
    rng: np.random.Generator | int | None = None,
    **options: Any,
) -> FlashTracker:
    """A flash tracker by name.

    Args:
        kind: one of :data:`FLASH_TRACKER_KINDS`:

            - ``icp``: point-to-point ICP on the whole cloud from the last estimate (the seed's
              baseline; :func:`~perception.estimation.linetrack.seed003_icp_config`);
            - ``seed003``: :class:`~.seed003.Seed003Tracker` (the seed's method);
            - ``p2plane``: our point-to-plane ICP on a 2,000-point subset, from the last estimate
              moved by the centroid's shift;
            - ``seed003+p2plane``: the seed's roll prior and voxel grid with point-to-plane ICP
              (gate widened to 2 m);
            - ``p2plane+cv+rays``: point-to-plane matched along the rays, constant-velocity
              prediction;
            - ``p2plane+cv+outline``: that, refined with the outline
              (:class:`~.outline.OutlineFlashTracker` without its filter);
            - ``p2plane+ekf+outline``: :class:`~.outline.OutlineFlashTracker` (the best).
        target: the target model.
        flash: the flash LiDAR's config; default :class:`~perception.config.FlashLidarConfig`.
        rng: generator (or seed) of the point subsets (not used by ``seed003*``).
        **options: keywords of the tracker's class, overriding the kind's (e.g. ``n_points``,
            ``max_pairs``, ``q_lines``, ``d_model``).

    Raises:
        ValueError: an unknown kind.
    """
    cfg = flash or FlashLidarConfig()
    if kind in ("seed003", "seed003+p2plane"):
        base: dict[str, Any] = {}
        if kind == "seed003+p2plane":
            base["icp_config"] = ICPConfig(max_correspondence_m=2.0)
        return Seed003Tracker(target, flash=cfg, **{**base, **options})
    if kind == "icp":
        base = {
            "icp_config": seed003_icp_config(flash_range_sigma(cfg)),
            "n_points": None,
            "motion": "previous",
        }
    elif kind == "p2plane":
        base = {"icp_config": ICPConfig(), "motion": "centroid"}
    elif kind == "p2plane+cv+rays":
        base = {"icp_config": ICPConfig(match_along_rays=True), "motion": "constant_velocity"}
    elif kind in ("p2plane+cv+outline", "p2plane+ekf+outline"):
        base = {"filtered": kind == "p2plane+ekf+outline"}
        return OutlineFlashTracker(target, flash=cfg, rng=rng, **{**base, **options})
    else:
        raise ValueError(
            f"flash tracker kind {kind!r}; expected one of {list(FLASH_TRACKER_KINDS)}"
        )
    return IcpFlashTracker(target, flash=cfg, rng=rng, **{**base, **options})
