"""Subcommands of the `vings` CLI: one module each, exposing ``register(subparsers)``."""
