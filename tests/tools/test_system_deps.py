"""``make install`` checks the system first (tools/check-system-deps): as root it installs what is missing with
apt-get; otherwise it stops at once and prints the exact command. ``ldconfig``, ``id`` and ``apt-get`` are
stand-ins on PATH here, so the test neither needs nor changes the machine's packages."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "tools" / "check-system-deps"
LIBRARIES = (
    "\tlibusb-1.0.so.0 (libc6,x86-64) => /lib/libusb-1.0.so.0\n\tlibgomp.so.1 (libc6,x86-64) => /lib/libgomp.so.1\n"
)


class FakeSystem:
    """A folder of stand-in commands: the library cache is a file, apt-get records its calls and 'installs'."""

    def __init__(self, root: Path, uid: int, libraries: str) -> None:
        self.bin = root / "bin"
        self.bin.mkdir()
        self.cache = root / "ld.so.cache.txt"
        self.cache.write_text(libraries)
        self.apt_log = root / "apt.log"
        self._command("ldconfig", f'cat "{self.cache}"')
        self._command("id", f"echo {uid}")
        install = f"printf '%s' '{LIBRARIES}' > \"{self.cache}\""
        self._command("apt-get", f'echo "$@" >> "{self.apt_log}"; [ "$1" = install ] && {install}; exit 0')
        # The web tools are present here (their absence is a test of its own): node 20, npm, a chromium.
        self._command("node", "echo 20")
        self._command("npm", "exit 0")
        self.chromium = self.bin / "chromium"
        self._command("chromium", "exit 0")

    def _command(self, name: str, body: str) -> None:
        path = self.bin / name
        path.write_text(f"#!/bin/sh\n{body}\n")
        path.chmod(0o755)

    def run(self, *args: str) -> subprocess.CompletedProcess[str]:
        env = {**os.environ, "PATH": f"{self.bin}{os.pathsep}{os.environ['PATH']}", "PYTHON": sys.executable,
               "CHROMIUM": str(self.chromium)}  # fmt: skip
        return subprocess.run([str(SCRIPT), *args], env=env, capture_output=True, text=True, timeout=60)

    def apt_calls(self) -> list[str]:
        return self.apt_log.read_text().splitlines() if self.apt_log.exists() else []


@pytest.mark.parametrize("uid", [0, 1000])
def test_nothing_missing_nothing_done(tmp_path: Path, uid: int) -> None:
    system = FakeSystem(tmp_path, uid=uid, libraries=LIBRARIES)
    done = system.run()
    assert done.returncode == 0, done.stderr
    assert system.apt_calls() == []


def test_a_long_library_cache_is_read_whole(tmp_path: Path) -> None:
    """A cache listing longer than a pipe buffer, with the libraries near its top: piped into ``grep -q`` under
    ``pipefail``, ldconfig died of SIGPIPE and the libraries read as missing (the CI failure this guards)."""
    filler = "".join(f"\tlibfiller{i}.so.1 (libc6,x86-64) => /lib/libfiller{i}.so.1\n" for i in range(8000))
    system = FakeSystem(tmp_path, uid=1000, libraries=LIBRARIES + filler)
    assert system.cache.stat().st_size > 4 * 65536
    done = system.run()
    assert done.returncode == 0, done.stderr
    assert system.apt_calls() == []


def test_not_root_stops_at_once_with_the_command(tmp_path: Path) -> None:
    system = FakeSystem(tmp_path, uid=1000, libraries="")
    done = system.run()
    assert done.returncode == 1
    assert "sudo apt-get install -y libusb-1.0-0 libgomp1" in done.stderr
    assert system.apt_calls() == [], "a user who is not root is told, not sudo-prompted"


def test_root_installs_what_is_missing(tmp_path: Path) -> None:
    system = FakeSystem(tmp_path, uid=0, libraries="\tlibgomp.so.1 (libc6,x86-64) => /lib/libgomp.so.1\n")
    done = system.run()
    assert done.returncode == 0, done.stderr
    assert system.apt_calls() == ["update -qq", "install -y libusb-1.0-0 -qq"]


def test_missing_chromium_is_installed_as_root(tmp_path: Path) -> None:
    system = FakeSystem(tmp_path, uid=0, libraries=LIBRARIES)
    system.chromium.unlink()
    # The stand-in apt-get "installs" it.
    system._command("apt-get", f'echo "$@" >> "{system.apt_log}"; [ "$1" = install ] && touch "{system.chromium}" '
                    f'&& chmod +x "{system.chromium}"; exit 0')  # fmt: skip
    done = system.run()
    assert done.returncode == 0, done.stderr
    assert system.apt_calls() == ["update -qq", "install -y chromium -qq"]


def test_old_node_is_refused(tmp_path: Path) -> None:
    system = FakeSystem(tmp_path, uid=0, libraries=LIBRARIES)
    system._command("node", 'if [ "$1" = -v ]; then echo v16.0.0; else echo 16; fi')
    done = system.run("--web")
    assert done.returncode == 1
    assert "needs node 18 or later" in done.stderr


def test_only_the_web_build_needs_node(tmp_path: Path) -> None:
    """The Python checks never look at node: with an unusable one they pass untouched; the web build's refuses it."""
    system = FakeSystem(tmp_path, uid=0, libraries=LIBRARIES)
    system._command("node", 'if [ "$1" = -v ]; then echo v16.0.0; else echo 16; fi')
    system._command("npm", "exit 1")
    done = system.run()
    assert done.returncode == 0, done.stderr
    assert system.apt_calls() == []
    assert system.run("--web").returncode == 1


def test_the_readme_session_tools_are_installed_as_root(tmp_path: Path) -> None:
    """curl, jq and zip (the README's curl session): on a PATH that has none of them, apt-get installs them."""
    system = FakeSystem(tmp_path, uid=0, libraries=LIBRARIES)
    base = tmp_path / "base"  # only what the script and the stand-ins run, without curl, jq and zip
    base.mkdir()
    for name in ("bash", "sh", "cat", "env", "touch", "chmod", "printf"):
        found = shutil.which(name)
        assert found is not None
        (base / name).symlink_to(found)
    installed = " ".join(f'touch "{system.bin}/{t}" && chmod +x "{system.bin}/{t}";' for t in ("curl", "jq", "zip"))
    system._command("apt-get", f'echo "$@" >> "{system.apt_log}"; [ "$1" = install ] && {{ {installed} }}; exit 0')
    env = {"PATH": f"{system.bin}{os.pathsep}{base}", "PYTHON": sys.executable, "CHROMIUM": str(system.chromium)}
    done = subprocess.run([str(SCRIPT)], env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert system.apt_calls() == ["update -qq", "install -y curl jq zip -qq"]
