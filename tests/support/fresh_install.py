"""The project as a user installs it: a wheel built from the sources, installed with an extra into a new virtual
environment, away from the repository (no editable install, no source tree on the path).

Built once per test run (made_once.py: one build for both pytest-xdist processes): the tests of the API install
and of the shipped migrations share it. Pip reads the same indexes and constraints as ``make install``, so on a
machine that has installed the project before, every download is already in pip's cache or local wheel folders.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from made_once import made_once

REPO = Path(__file__).resolve().parents[2]
SOURCES = ("pyproject.toml", "README.md", "panogs_core", "service", "worker")
INSTALL_TIMEOUT_S = 900  # a cold pip cache downloads the service's dependencies


@dataclass(frozen=True)
class FreshInstall:
    """A virtual environment with ``panogs[extras]`` installed from a wheel."""

    root: Path
    extras: str

    @property
    def python(self) -> Path:
        return self.root / "bin" / "python"

    @property
    def panogs(self) -> Path:
        return self.root / "bin" / "panogs"

    def env(self) -> dict[str, str]:
        """The environment to run it in: this machine's, without anything that points at the repository or the
        development environment."""
        drop = {"PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME"}
        clean = {k: v for k, v in os.environ.items() if k not in drop and not k.startswith("PANOGS_")}
        return {**clean, "PATH": f"{self.root / 'bin'}{os.pathsep}{clean.get('PATH', '')}"}

    def run(self, code: str, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
        """``python -c code`` in this environment."""
        argv = [str(self.python), "-c", code]
        return subprocess.run(argv, cwd=cwd, env=self.env(), capture_output=True, text=True, timeout=timeout)


def build_wheel(out: Path) -> Path:
    """The project's wheel, built from a copy of its sources: a stale ``build/`` folder cannot leak into it, and
    the repository is left as it was."""
    src = out / "src"
    src.mkdir(parents=True)
    for name in SOURCES:
        source = REPO / name
        if source.is_dir():
            shutil.copytree(source, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(source, src / name)
    dist = out / "dist"
    argv = [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(dist), str(src)]
    subprocess.run(argv, check=True, capture_output=True, timeout=300)
    (wheel,) = dist.glob("panogs-*.whl")
    return wheel


def install(tmp_path_factory: pytest.TempPathFactory, extras: str) -> FreshInstall:
    """``panogs[extras]`` from a freshly built wheel in a new virtual environment, made once per test run."""
    out = made_once(tmp_path_factory, f"fresh-{extras.replace(',', '-')}", lambda folder: _install(folder, extras))
    return FreshInstall(out / "venv", extras)


def _install(out: Path, extras: str) -> FreshInstall:
    """``panogs[extras]`` from a freshly built wheel in a new virtual environment under ``out``."""
    wheel = build_wheel(out)
    venv = FreshInstall(out / "venv", extras)
    subprocess.run([sys.executable, "-m", "venv", str(venv.root)], check=True, timeout=300)
    # --no-compile: pip would byte-compile every module of every installed package, most of which no test imports;
    # Python compiles what the tests import when they import it.
    argv = [str(venv.python), "-m", "pip", "install", "-q", "--no-compile", "--disable-pip-version-check",
            "-c", str(REPO / "constraints.txt"), f"{wheel}[{extras}]"]  # fmt: skip
    done = subprocess.run(argv, env=venv.env(), capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S)
    if done.returncode != 0:
        raise RuntimeError(f"pip install {wheel.name}[{extras}] failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    return venv
