"""Exception hierarchy: every error confnav raises derives from :class:`ConfnavError`.

Services turn these into error replies / status codes on the wire; the CLI prints their
message and exits non-zero.
"""

from __future__ import annotations


class ConfnavError(Exception):
    """Root of all confnav errors."""


class WorkspaceError(ConfnavError, ValueError):
    """The workspace definition is invalid (names the polygon and the problem)."""


class SolverError(ConfnavError, RuntimeError):
    """The conformal map could not be computed to the requested accuracy."""


class CrowdingError(SolverError):
    """Some circle of the circle domain is too small for double precision (crowding)."""


class ConvergenceError(SolverError):
    """An iteration (GMRES or the Koebe-type sweeps) did not converge."""


class UnresolvedCrowdingError(ConvergenceError, CrowdingError):
    """A disk map could not resolve a crowded region: whole boundaries land in a thin band
    next to the unit circle (a region reached through a narrow passage). Finer meshes rarely
    help; an atlas (``confnav atlas``, or the transform service, automatically) does."""


class NavigationError(ConfnavError, ValueError):
    """A navigation request is invalid (goal outside free space, bad parameter, ...)."""


class SerializationError(ConfnavError, ValueError):
    """A serialized map or workspace cannot be loaded (wrong format, version or content)."""


class GapError(SolverError):
    """Two boundaries come closer than the mesh can resolve (names both and the gap)."""


class MapMismatchError(ConfnavError, ValueError):
    """A map is used with a workspace other than the one it was solved for."""


def fmt_point(z: complex) -> str:
    """A point for an error message, ``(x, y)`` as the user typed it, never ``x+yj``."""
    return f"({z.real:.6g}, {z.imag:.6g})"
