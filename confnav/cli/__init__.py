"""The ``confnav`` command line: ``app`` builds the parser from one module per command
group (``solve``, ``simulate``, ``import_map``, ``atlas``, ``services``, ``recording``)."""

from confnav.cli.app import main

__all__ = ["main"]
