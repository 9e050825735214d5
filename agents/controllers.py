"""Scripted controllers by name: ``make_controller("glideslope", cfg)``.

Campaigns and the CLI name their controller in YAML; this registry turns the name into an object
(``obs -> action`` with ``reset()``). Modules are imported only when their controller is asked for,
so a controller that is not installed (or not written yet) costs nothing until it is used, and then
fails with one clear message.

Names:
    ``glideslope``: :class:`agents.glideslope.GlideslopeController` (with the bearing-mode law of
        :mod:`agents.bearing_guidance` far out, before acquisition: it flies Rendezvous-v0 from
        ~500 m on the full pipeline).
    ``lqr``: :class:`agents.lqr.LQRController` (the same bearing-mode law far out).
    ``sync``: :class:`agents.sync.SyncController` (synchronised approach to a tumbling port).
    ``fly_around``: :class:`agents.fly_around.FlyAroundController` (undocking and fly-around,
        FlyAround-v0).
    ``sb3:<path>``: a saved stable-baselines3 policy (``model.zip`` or its run folder) through
        :func:`agents.policies.load_policy`, deterministic actions.
    ``<module>:<Class>``: any importable class taking ``(cfg)``.

Example:
    >>> from perception.config import load_config
    >>> from agents.controllers import make_controller
    >>> ctrl = make_controller("glideslope", load_config("final_approach", env__perception="truth"))
    >>> callable(ctrl)
    True
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

from perception.config import MissionConfig

__all__ = ["CONTROLLERS", "controller_names", "make_controller"]

#: name -> "module:attribute" of a class (or factory) called with the mission config.
CONTROLLERS: dict[str, str] = {
    "glideslope": "agents.glideslope:GlideslopeController",
    "lqr": "agents.lqr:LQRController",
    "sync": "agents.sync:SyncController",
    "fly_around": "agents.fly_around:FlyAroundController",
}


def controller_names() -> list[str]:
    """The registered names (whether or not their module is importable yet)."""
    return sorted(CONTROLLERS)


def _resolve(spec: str, name: str) -> Callable[..., Any]:
    module_name, _, attr = spec.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(
            f"controller {name!r} needs module {module_name!r}, which cannot be imported ({exc})"
        ) from None
    factory = getattr(module, attr, None)
    if not callable(factory):
        # ValueError, as for every bad name: callers report a bad controller name in one line.
        raise ValueError(  # noqa: TRY004
            f"controller {name!r}: module {module_name!r} has no callable {attr!r}"
        )
    return factory


def make_controller(name: str, cfg: MissionConfig) -> Callable[..., Any]:
    """Build the controller called ``name`` for the mission ``cfg``.

    Args:
        name: a registered name (:data:`CONTROLLERS`), ``sb3:<path>`` for a saved SB3 policy, or
            ``module:Class`` for any importable controller class.
        cfg: the resolved mission config of the env the controller will fly.

    Returns:
        A callable ``obs -> action`` (normalised to ``[-1, 1]``), usually with ``reset()``.

    Raises:
        ValueError: an unknown name, or a module that cannot be imported; the message lists the
            known names.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"controller={name!r}; expected a non-empty name")
    if name.startswith("sb3:"):
        from agents.policies import load_policy

        return load_policy(name[4:], cfg=cfg)
    if name in CONTROLLERS:
        return _resolve(CONTROLLERS[name], name)(cfg)
    if ":" in name:
        return _resolve(name, name)(cfg)
    raise ValueError(
        f"controller={name!r} is unknown; expected one of {', '.join(controller_names())}, "
        "'sb3:<path to model.zip>' or 'module:Class'"
    )
