"""Subcommands of ``tridar-env``; every module here registers itself with ``tridar_env.cli.command``."""
