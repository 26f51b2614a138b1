"""The wheel, as a user gets it: built from the package folders, installed into a fresh venv without the
editable install, run from outside the checkout (so no folder of the checkout can stand in for a module).

The fresh venv borrows the project's dependencies from this venv's site-packages through a plain path
line in a .pth file: a path line only extends sys.path, it does not run that directory's .pth files, so
the editable finder of /work/main stays off and `octolog` can only come from the wheel. About 20 s.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tomllib
import zipfile
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
PACKAGE_DIR: dict[str, str] = PYPROJECT["tool"]["setuptools"]["package-dir"]
NAME, VERSION = PYPROJECT["project"]["name"], PYPROJECT["project"]["version"]
TIMEOUT = 120


@dataclass(frozen=True)
class Installed:
    src: Path  # the copy of the checkout the wheel was built from
    wheel: Path
    python: Path  # the fresh venv's interpreter
    bin: Path
    site: Path  # the fresh venv's site-packages
    cwd: Path  # outside the checkout
    env: dict[str, str]

    def run(self, *argv: str | Path) -> subprocess.CompletedProcess:
        proc = subprocess.run([str(a) for a in argv], cwd=self.cwd, env=self.env, capture_output=True, text=True,
                              timeout=TIMEOUT, check=False)
        command = " ".join(map(str, argv))
        assert proc.returncode == 0, f"{command} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
        return proc

    def python_c(self, code: str) -> str:
        return self.run(self.python, "-c", code).stdout


def _source_modules(src: Path) -> set[str]:
    """`octolog/...py` paths the wheel must hold: every .py file under the package-dir folders."""
    out = set()
    for package, folder in PACKAGE_DIR.items():
        for path in (src / folder).rglob("*.py"):
            out.add("/".join([*package.split("."), *path.relative_to(src / folder).parts]))
    return out


def _pip(*argv: str | Path, cwd: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "pip", *map(str, argv), "--disable-pip-version-check", "-q"],
                          cwd=cwd, capture_output=True, text=True, timeout=TIMEOUT, check=False)
    command = " ".join(map(str, argv))
    assert proc.returncode == 0, f"pip {command} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Installed:
    tmp = tmp_path_factory.mktemp("wheel")
    # Build from a copy of exactly what packaging reads, so the build leaves no build/ or egg-info in
    # the checkout. setuptools comes from the package index in pip's isolated build environment
    # (this venv's setuptools is older than pyproject's build requirement).
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", PYPROJECT["project"]["readme"]):
        shutil.copy2(ROOT / name, src / name)
    for folder in sorted(set(PACKAGE_DIR.values())):
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    dist = tmp / "dist"
    _pip("wheel", src, "--no-deps", "-w", dist, cwd=tmp)
    (wheel,) = dist.glob("*.whl")

    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", venv], check=True, timeout=TIMEOUT)
    python = venv / "bin" / "python"
    query = "import sysconfig; print(sysconfig.get_paths()['purelib'])"
    site = Path(subprocess.run([python, "-c", query], capture_output=True, text=True, check=True).stdout.strip())
    deps = dict.fromkeys(sysconfig.get_paths()[key] for key in ("purelib", "platlib"))  # this venv's
    (site / "octolog_test_dependencies.pth").write_text("".join(f"{p}\n" for p in deps))
    _pip("--python", python, "install", "--no-deps", "--no-index", wheel, cwd=tmp)

    cwd = tmp / "elsewhere"
    cwd.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    env.update(PYTHONNOUSERSITE="1", RERUN_DISABLE_ANALYTICS="1", PATH=f"{venv / 'bin'}{os.pathsep}{env['PATH']}")
    return Installed(src, wheel, python, venv / "bin", site, cwd, env)


def test_wheel_adds_one_top_level_package(installed: Installed):
    with zipfile.ZipFile(installed.wheel) as zf:
        names = zf.namelist()
    top = {name.split("/")[0] for name in names}
    assert top == {NAME, f"{NAME}-{VERSION}.dist-info"}, f"wheel top-level entries: {sorted(top)}"
    modules = {n for n in names if n.endswith(".py")}
    missing = _source_modules(installed.src) - modules
    assert not missing, f"modules left out of the wheel (a package missing from pyproject.toml?): {sorted(missing)}"
    own = {p.name for p in (installed.src / PACKAGE_DIR["octolog.schemas"] / "msg").glob("*.msg")}
    assert own, "no schemas/msg/*.msg in the checkout"
    shipped = {Path(n).name for n in names if n.startswith(f"{NAME}/schemas/msg/") and n.endswith(".msg")}
    assert shipped == own, f".msg files in the wheel {sorted(shipped)} != schemas/msg {sorted(own)}"


def test_every_module_imports_from_the_fresh_venv(installed: Installed):
    with zipfile.ZipFile(installed.wheel) as zf:
        modules = sorted(n[:-3].replace("/", ".").removesuffix(".__init__") for n in zf.namelist()
                         if n.endswith(".py") and not n.endswith("__main__.py"))
    code = ("import importlib, json, sys\n"
            f"for m in {modules!r}:\n"
            "    try:\n"
            "        print(json.dumps([m, importlib.import_module(m).__file__, None]))\n"
            "    except Exception as exc:\n"
            "        print(json.dumps([m, None, f'{type(exc).__name__}: {exc}']))\n"
            "print(json.dumps(sorted(k for k in sys.modules if '__editable__' in k)))\n")
    *rows, editable = (json.loads(line) for line in installed.python_c(code).splitlines())
    assert editable == [], f"the editable install leaked into the fresh venv: {editable}"
    assert [m for m, _, _ in rows] == modules
    problems = [f"{m}: {error}" for m, _, error in rows if error]
    for module, file, _ in rows:
        if file and not (Path(file).is_relative_to(installed.site) and not Path(file).resolve().is_relative_to(ROOT)):
            problems.append(f"{module}: imported from {file}, not from the fresh venv's {installed.site}")
    assert not problems, "modules that do not import from the installed wheel:\n" + "\n".join(problems)


def test_cli_runs_from_the_fresh_venv(installed: Installed):
    octolog = installed.bin / "octolog"
    help_text = installed.run(octolog, "--help").stdout
    for command in ("run", "replay", "record", "import", "eval", "info", "router"):
        assert command in help_text
    assert "usage:" in installed.run(installed.python, "-m", "octolog", "--help").stdout

    # a tiny TUM pair: ground truth on a helix, the estimate the same path moved rigidly by 1 m
    gt, est = installed.cwd / "gt.txt", installed.cwd / "est.txt"
    gt_lines, est_lines = [], []
    for i in range(30):
        t, x, y, z = 1.0 + 0.1 * i, 0.1 * i, 0.05 * (i % 7), 0.02 * i * i / 30
        gt_lines.append(f"{t:.4f} {x:.4f} {y:.4f} {z:.4f} 0 0 0 1")
        est_lines.append(f"{t:.4f} {x + 1:.4f} {y:.4f} {z:.4f} 0 0 0 1")
    gt.write_text("\n".join(gt_lines) + "\n")
    est.write_text("\n".join(est_lines) + "\n")
    report = installed.run(octolog, "eval", est.name, gt.name).stdout
    assert "ATE RMSE 0.00 cm (n=30;" in report, report


def test_message_definitions_are_installed(installed: Installed):
    code = ("from octolog.schemas import codec\n"
            "print(codec.MSG_DIR)\n"
            "store = codec.typestore()\n"
            "for p in sorted(codec.MSG_DIR.glob('*.msg')):\n"
            "    print(p.stem, f'{codec.VENDORED.get(p.stem, codec.OWN_PACKAGE)}/msg/{p.stem}' in store.types)\n")
    msg_dir, *rows = installed.python_c(code).splitlines()
    assert Path(msg_dir).is_relative_to(installed.site), msg_dir
    own = sorted(p.stem for p in (installed.src / PACKAGE_DIR["octolog.schemas"] / "msg").glob("*.msg"))
    assert rows == [f"{stem} True" for stem in own]
