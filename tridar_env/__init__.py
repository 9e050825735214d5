"""tridar-env: a Gymnasium environment for spacecraft rendezvous and docking seen through TriDAR.

``import tridar_env`` registers the ids of :data:`ENV_IDS` (``TriDAR/FinalApproach-v0``,
``TumblingTarget-v0``, ``Rendezvous-v0``, ``FarRendezvous-v0``, ``FlyAround-v0``, ``Seed003-v0``)
with Gymnasium (``gymnasium.make`` builds a :class:`DockingEnv`;
``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")`` a :class:`TruthVectorEnv`).
"""

from tridar_env.env import OBSERVATION_STRUCTURE, DockingEnv
from tridar_env.registration import ENV_IDS, register_envs
from tridar_env.vector import TruthVectorEnv

__version__ = "0.1.0"
__all__ = ["ENV_IDS", "OBSERVATION_STRUCTURE", "DockingEnv", "TruthVectorEnv", "register_envs"]

register_envs()
