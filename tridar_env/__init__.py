"""tridar-env: a Gymnasium environment for spacecraft rendezvous and docking seen through TriDAR."""

__version__ = "0.1.0"
