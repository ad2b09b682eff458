"""A non-editable install ships every package, the recipes and the verifier examples, under one top-level import
name: `posttrain` (PyPI's `verifiers`, the environments library, installs beside it)."""
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


PYPI_VERIFIERS = "verifiers==0.4.0"  # the environments library prime-rl builds on: a top-level `verifiers`
REQUIRE_ENV = "POSTTRAIN_REQUIRE_PYPI_VERIFIERS"  # .ci/run sets it: there the clash test must run, not skip


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The project's wheel, built from a copy of what the build reads: a checkout's build/ folder (setuptools reuses
    it) may hold stale packages, such as a top-level verifiers/ from before it was installed as posttrain.verifiers."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        if (ROOT / name).exists():
            shutil.copy2(ROOT / name, src / name)
    for name in ("posttrain", "verifiers", "recipes"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation",
                          "-q", "-w", str(tmp)], capture_output=True, text=True, timeout=300)
    if out.returncode != 0 and "No module named" in out.stderr and "setuptools" in out.stderr:
        pytest.skip("setuptools is not installed in this environment")
    assert out.returncode == 0, out.stderr
    return next(tmp.glob("posttrain-*.whl"))


@pytest.mark.slow
def test_wheel_contains_every_package_and_recipe(wheel, tmp_path):
    names = set(zipfile.ZipFile(wheel).namelist())
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert tops == {"posttrain"}, f"the wheel's top-level names are {sorted(tops)}: only posttrain is ours"
    for folder, installed in (("posttrain", "posttrain"), ("verifiers", "posttrain/verifiers")):
        for init in (ROOT / folder).rglob("*.py"):
            rel = f"{installed}/{init.relative_to(ROOT / folder).as_posix()}"
            assert rel in names, f"{rel} is not in the wheel: add its package to [tool.setuptools] packages"
    assert "posttrain/verifiers/README.md" in names
    for recipe in (ROOT / "recipes").glob("*.yaml"):
        assert f"posttrain/recipes/{recipe.name}" in names
    assert any(n.endswith("entry_points.txt") and "posttrain" in n for n in names)

    # The installed package finds its recipes and launch configs from anywhere (not only a checkout).
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    for launch in (ROOT / "recipes" / "launch").glob("*.yaml"):
        assert f"posttrain/recipes/launch/{launch.name}" in names
    code = ("from posttrain.config import list_recipes, recipes_dir; import sys; "
            "print(recipes_dir()); print(sorted(n for n, _ in list_recipes()))")
    got = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"})
    assert got.returncode == 0, got.stderr
    assert str(site) in got.stdout.splitlines()[0]
    assert "tiny-summarize" in got.stdout and "tiny-math" in got.stdout

    # The verifier layer, installed: posttrain.verifiers, without torch; no top-level `verifiers` of ours.
    code = ("import sys, posttrain.verifiers as v; print(v.__file__); print(v.get_verifier('math').name); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'verifiers')))")
    got = subprocess.run([sys.executable, "-S", "-c", code], cwd=tmp_path, capture_output=True, text=True,
                         timeout=120, env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"})
    assert got.returncode == 0, got.stderr
    assert got.stdout.splitlines() == [str(site / "posttrain" / "verifiers" / "__init__.py"), "math", "[]"]


@pytest.mark.slow
def test_installs_beside_pypi_verifiers(wheel, tmp_path):
    """pip installs our wheel and PyPI's `verifiers` into one environment: each imports as itself. (Their package's
    own dependencies are not installed: its top-level __init__ needs none, which is all the clash is about.)"""
    theirs = tmp_path / "theirs"
    got = subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", PYPI_VERIFIERS, "-d",
                          str(theirs)], capture_output=True, text=True, timeout=300)
    if got.returncode != 0:
        if os.environ.get(REQUIRE_ENV):
            pytest.fail(f"pip download {PYPI_VERIFIERS} failed: {got.stderr.strip().splitlines()[-1:]}")
        pytest.skip(f"{PYPI_VERIFIERS} cannot be downloaded here (no package index?)")
    site = tmp_path / "site"
    both = [str(wheel), str(next(theirs.glob("verifiers-*.whl")))]
    got = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-compile", "--target",
                          str(site), *both], capture_output=True, text=True, timeout=300)
    assert got.returncode == 0, got.stderr
    assert "already exists" not in got.stderr, got.stderr  # pip's word when two wheels write the same path
    code = ("import verifiers, posttrain.verifiers as ours; from importlib.metadata import version; "
            "print(verifiers.__file__); print(version('verifiers')); print(ours.__file__); "
            "print(ours.get_verifier('math').check(r'\\boxed{4}', '4').score)")
    got = subprocess.run([sys.executable, "-S", "-c", code], cwd=tmp_path, capture_output=True, text=True,
                         timeout=120, env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"})
    assert got.returncode == 0, got.stderr
    assert got.stdout.splitlines() == [str(site / "verifiers" / "__init__.py"), "0.4.0",
                                       str(site / "posttrain" / "verifiers" / "__init__.py"), "1.0"]
