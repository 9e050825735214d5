"""Benchmarks: scripts that print tables (median, p90, ratio to a peer run in the same process).

Each module has ``add_arguments(parser)`` and ``run(args) -> int`` and is reached through
``tridar-env bench <name>``. Performance goals live here, never in timed test assertions.
"""
