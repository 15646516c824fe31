"""The place-safe command line: parsing and printing only (the work is done by the library)."""

from place_safe.cli.app import main

__all__ = ["main"]
