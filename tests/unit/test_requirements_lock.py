"""The environment is pinned: results/ regenerate exactly only with the same packages.

Newer releases of the dependencies changed the workbench's numbers with the same code (the
compression scenario's deepflow RMSE went 0.15 -> 0.50 px when a fresh machine installed newer
releases of the unpinned dependencies; which package did it is not known). The Makefile installs
with ``-c requirements.lock``; these tests hold that the lock pins every package that shapes a
number and that the running environment is the locked one.
"""

from __future__ import annotations

import re
from importlib import metadata
from pathlib import Path

import pytest

LOCK = Path(__file__).resolve().parents[2] / "requirements.lock"

# The packages whose versions change the workbench's or the tool's numbers.
SHAPES_NUMBERS = ("mujoco", "opencv-contrib-python-headless", "numpy", "scipy", "numba", "pyrender",
                  "trimesh", "imageio-ffmpeg", "imageio", "snakemake", "pyopengl", "scikit-image")


def _normal(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _lock() -> dict[str, str]:
    pins = {}
    for line in LOCK.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        match = re.fullmatch(r"([A-Za-z0-9_.\-]+)==([^\s;]+)", line)
        assert match, f"requirements.lock: {line!r} is not NAME==VERSION"
        pins[_normal(match.group(1))] = match.group(2)
    return pins


def test_lock_pins_every_package_that_shapes_a_number() -> None:
    pins = _lock()
    missing = [name for name in SHAPES_NUMBERS if _normal(name) not in pins]
    assert not missing, f"requirements.lock lacks {missing}"
    # One OpenCV distribution only (the contrib build has DeepFlow; two side by side collide).
    others = [name for name in pins if name.startswith("opencv") and name != "opencv-contrib-python-headless"]
    assert not others, f"requirements.lock pins a second OpenCV distribution: {others}"


def test_lock_is_not_the_project_itself() -> None:
    assert "refflow" not in _lock(), "requirements.lock must not pin the project (it is installed editable)"


@pytest.mark.parametrize("name", SHAPES_NUMBERS)
def test_installed_version_is_the_locked_one(name: str) -> None:
    pinned = _lock()[_normal(name)]
    try:
        installed = metadata.version(name)
    except metadata.PackageNotFoundError:
        pytest.fail(f"{name} is locked at {pinned} but not installed: run `make .venv/.installed`")
    assert installed == pinned, (f"{name} {installed} is installed, requirements.lock pins {pinned}: "
                                 "reinstall with `make .venv/.installed`, or after a deliberate upgrade "
                                 "`make lock` and regenerate results/ with `make all`")
