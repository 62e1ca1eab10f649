"""Provenance of a benchmark result: the commit it was measured at and the machine's load."""

from __future__ import annotations

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def git(*args: str) -> str:
    """Output of ``git ARGS`` in the repository ("" when git or the repository is missing)."""
    try:
        return subprocess.run(
            ["git", *args], cwd=ROOT, capture_output=True, text=True, check=True, timeout=10
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def commit() -> str:
    """The commit of HEAD ("unknown" outside a git checkout)."""
    return git("rev-parse", "HEAD") or "unknown"


def loadavg() -> str:
    """The 1, 5 and 15 minute load averages and process counts (/proc/loadavg)."""
    try:
        return Path("/proc/loadavg").read_text().strip()
    except OSError:
        return "unknown"
