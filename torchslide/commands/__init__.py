"""Subcommand implementations of the ``torchslide`` CLI (one module per command; see torchslide.cli)."""
