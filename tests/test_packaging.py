"""The package as users get it: a wheel built from this checkout, installed into a fresh venv.

``confnav.services`` and ``confnav.schemas`` live in the top-level ``services/`` and
``schemas/`` directories and are mapped into the package by setuptools' ``package-dir``; this
checks the mapping survives a real wheel (no symlinks, no second import name).

The test venv is isolated (``system_site_packages=False``) and needs no network: the
dependencies are the ones the running interpreter imports, made visible to the new venv by a
``.pth`` file listing the running interpreter's site directories (the directories every
dependency was imported from), while confnav itself comes only from the wheel. This works
whatever the running environment is: a fresh venv (``pip install -e '.[dev]'``, where
``system_site_packages=True`` would see the system Python's packages, not the venv's), a
venv on system packages, or the system Python.
"""

from __future__ import annotations

import importlib
import importlib.metadata
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


#: What the wheel imports at run time (pyproject dependencies, by import name).
DEPENDENCIES = (
    "numpy",
    "scipy",
    "shapely",
    "matplotlib",
    "pydantic",
    "zenoh",
    "mcap",
    "yaml",
    "threadpoolctl",
)


def _setuptools_version() -> tuple[int, ...]:
    try:
        text = importlib.metadata.version("setuptools")
    except importlib.metadata.PackageNotFoundError:
        return ()
    return tuple(int(p) for p in text.split(".")[:2] if p.isdigit())


def dependency_dirs() -> list[Path]:
    """The sys.path entries the dependencies are imported from (site-packages and the like),
    never this checkout (an editable install puts it on sys.path)."""
    entries = []
    for entry in map(Path, sys.path):
        try:
            entry = entry.resolve()
        except OSError:
            continue
        if entry.is_dir() and entry != ROOT:
            entries.append(entry)
    dirs: list[Path] = []
    for name in DEPENDENCIES:
        mod = importlib.import_module(name)
        origin = Path(mod.__file__ or "").resolve()
        # the most specific entry: site-packages, not the standard library above it
        holders = [e for e in entries if origin.is_relative_to(e)]
        assert holders, f"{name} ({origin}) is not under any sys.path entry"
        best = max(holders, key=lambda e: len(e.parts))
        if best not in dirs:
            dirs.append(best)
    return dirs


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
    # build with this interpreter's setuptools when it is recent enough (no network); else pip
    # builds in isolation and fetches setuptools from the configured index
    isolation = ["--no-build-isolation"] if _setuptools_version() >= (69,) else []
    _run(
        sys.executable, "-m", "pip", "wheel", "--no-deps", *isolation, "-q", "-w", dist, src,
        cwd=tmp_path,
    )  # fmt: skip
    (wheel,) = dist.glob("confnav-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    assert top == {"confnav", wheel.name.removesuffix("-py3-none-any.whl") + ".dist-info"}
    assert "confnav/services/transform.py" in names
    assert "confnav/schemas/messages.py" in names
    assert "confnav/py.typed" in names

    # an isolated venv; the dependencies are this interpreter's (a .pth file appends their
    # directories to the new venv's sys.path, after its own site-packages), confnav itself
    # comes only from the wheel
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True, system_site_packages=False).create(env_dir)
    bindir = env_dir / ("Scripts" if sys.platform == "win32" else "bin")
    py = bindir / "python"
    site_dir = Path(
        _run(
            py, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))", cwd=tmp_path
        ).strip()
    )
    deps = dependency_dirs()
    (site_dir / "zz_confnav_test_deps.pth").write_text("".join(f"{d}\n" for d in deps))
    _run(py, "-m", "pip", "install", "-q", "--no-deps", "--no-index", wheel, cwd=tmp_path)
    # the venv does not see this checkout: a confnav import that works comes from the wheel
    path = _run(py, "-c", "import sys; print('\\n'.join(sys.path))", cwd=tmp_path)
    assert str(ROOT) not in path.splitlines(), path
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
