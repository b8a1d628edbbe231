"""Install into an existing environment (issue 25): the wheel built from this source tree
installs into a fresh venv, ``import dfusion`` takes it from there and the ``dfusion``
command it installs runs a scenario; its metadata is complete; building and an editable
install print no setuptools banner.

Lean: ``pip wheel --no-deps`` builds only dfusion (pip fetches the build backend,
setuptools, from the index as any build does); the fresh venv is made without pip and
installed into with this interpreter's ``pip --python``, and reaches the dependencies
already installed here through a ``.pth`` line, so numpy & co. are not downloaded again.
The source is copied first, so the build leaves no ``build/`` in the working tree.
"""
from __future__ import annotations

import email
import os
import shutil
import subprocess
import sys
import sysconfig
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The venv's interpreter sees neither this source tree nor a PYTHONPATH of the test run.
ENV = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
BANNER = ("!!\n", "*" * 20, "InformationOnly", "SetuptoolsDeprecationWarning")


def _pip(*args: str, cwd: Path) -> str:
    r = subprocess.run([sys.executable, "-m", "pip", "--disable-pip-version-check", *args], cwd=cwd,
                       capture_output=True, text=True, timeout=300, env=ENV)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return r.stdout + r.stderr


def test_the_wheel_installs_into_a_fresh_venv_and_simulates(tmp_path: Path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, src / name)
    shutil.copytree(ROOT / "dfusion", src / "dfusion", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    out = _pip("wheel", "-v", "--no-deps", "-w", str(tmp_path / "dist"), str(src), cwd=tmp_path)
    assert not any(b in out for b in BANNER), "the build prints a setuptools banner"
    [wheel] = (tmp_path / "dist").glob("dfusion-*.whl")

    # complete metadata: what pyproject.toml declares, the licence text, the command
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        meta = email.message_from_bytes(z.read(next(n for n in names if n.endswith(".dist-info/METADATA"))))
        entry = z.read(next(n for n in names if n.endswith(".dist-info/entry_points.txt"))).decode()
    assert meta["Name"] == "dfusion" and meta["Summary"] and meta["License-Expression"] == "MIT"
    assert meta["Requires-Python"] == ">=3.11" and meta["Author"] and meta["Keywords"]
    assert len(meta.get_all("Classifier")) >= 5 and meta.get_all("License-File") == ["LICENSE"]
    assert "# dfusion" in meta.get_payload()   # the README is the description
    base = {r.split(";")[0].replace(" ", "") for r in meta.get_all("Requires-Dist") if "extra ==" not in r}
    assert len(base) == len(project["dependencies"]) and "foxglove-schemas-protobuf>=0.3" in base
    assert "dfusion = dfusion.cli:main" in entry
    packages = {str(p.parent.relative_to(ROOT)) for p in (ROOT / "dfusion").rglob("__init__.py")}
    assert packages <= {str(Path(n).parent) for n in names}, "a package is missing from the wheel"

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    python = venv / "bin" / "python"
    _pip("--python", str(python), "install", "--no-deps", "--no-index", str(wheel), cwd=tmp_path)
    site = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True, env=ENV).stdout.strip()
    # the dependencies installed here, after the venv's own site-packages (dfusion comes from the wheel)
    (Path(site) / "_deps_of_the_test.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    r = subprocess.run([str(python), "-c", "import dfusion, dfusion.viz.foxglove, dfusion.bags; print(dfusion.__file__)"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120, env=ENV)
    assert r.returncode == 0, r.stderr
    assert Path(r.stdout.strip()).is_relative_to(venv), r.stdout
    r = subprocess.run([str(venv / "bin" / "dfusion"), "simulate", str(ROOT / "topologies" / "chain3.scenario.toml"),
                        "--duration", "3", "-q"], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                       env=ENV)
    assert r.returncode == 0, r.stderr
    assert "RMSE [m]" in r.stdout and "centralized" in r.stdout

    # an editable install (what make does) prints no banner either
    out = _pip("--python", str(python), "install", "-v", "--no-deps", "-e", str(src), cwd=tmp_path)
    assert not any(b in out for b in BANNER), "the editable install prints a setuptools banner"
