"""The package as users get it: a wheel built from this checkout, installed into a fresh venv.

``confnav.services`` and ``confnav.schemas`` live in the top-level ``services/`` and
``schemas/`` directories and are mapped into the package by setuptools' ``package-dir``; this
checks the mapping survives a real wheel (no symlinks, no second import name).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.slow


def _run(*args: str | Path, cwd: Path) -> str:
    proc = subprocess.run(
        [str(a) for a in args], cwd=cwd, capture_output=True, text=True, timeout=240
    )
    assert proc.returncode == 0, f"{args}: {proc.stdout}\n{proc.stderr}"
    return proc.stdout


def test_wheel_installs_into_fresh_venv_and_runs(tmp_path: Path) -> None:
    # build from a copy: setuptools writes build/ next to the sources
    src = tmp_path / "src"
    src.mkdir()
    skip = shutil.ignore_patterns(
        ".git", "build", "dist", "out", "*.egg-info", "__pycache__", "*.mcap"
    )
    for part in ("pyproject.toml", "README.md", "confnav", "services", "schemas"):
        if (ROOT / part).is_dir():
            shutil.copytree(ROOT / part, src / part, ignore=skip)
        else:
            shutil.copy2(ROOT / part, src / part)
    dist = tmp_path / "dist"
    _run(sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", dist, src, cwd=tmp_path)
    (wheel,) = dist.glob("confnav-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    assert top == {"confnav", wheel.name.removesuffix("-py3-none-any.whl") + ".dist-info"}
    assert "confnav/services/transform.py" in names
    assert "confnav/schemas/messages.py" in names
    assert "confnav/py.typed" in names

    # dependencies come from this interpreter's site-packages; confnav itself only from the wheel
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True, system_site_packages=True).create(env_dir)
    bindir = env_dir / ("Scripts" if sys.platform == "win32" else "bin")
    py = bindir / "python"
    _run(py, "-m", "pip", "install", "-q", "--no-deps", "--no-index", wheel, cwd=tmp_path)
    where = _run(
        py, "-c", "import confnav, confnav.services; print(confnav.__file__)", cwd=tmp_path
    )
    assert Path(where.strip()).is_relative_to(env_dir), where

    version = _run(bindir / "confnav", "--version", cwd=tmp_path)
    assert version.startswith("confnav ")
    out = tmp_path / "schemas"
    _run(bindir / "confnav", "schemas", "export", out, cwd=tmp_path)
    exported = sorted(p.name for p in out.glob("*.json"))
    assert {"confnav.Goal.schema.json", "confnav.TransformSolution.schema.json"} <= set(exported)
    goal = json.loads((out / "confnav.Goal.schema.json").read_text())
    assert goal["properties"]["ws_id"]["type"] == "string"
