"""Consumers of the environment: scripted GN&C controllers, SB3 training, evaluation, campaigns."""
