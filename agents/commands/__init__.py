"""Subcommands of ``tridar-env``; every module here registers itself with ``agents.cli.command``."""
