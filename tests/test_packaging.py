"""A non-editable install ships every package, the recipes and the verifier examples, under one top-level import
name: `posttrain` (PyPI's `verifiers`, the environments library, installs beside it)."""
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_wheel_contains_every_package_and_recipe(tmp_path):
    # Built from a copy of what the build reads: a checkout's build/ folder (setuptools reuses it) may hold stale
    # packages, such as a top-level verifiers/ from before it was installed as posttrain.verifiers.
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        if (ROOT / name).exists():
            shutil.copy2(ROOT / name, src / name)
    for name in ("posttrain", "verifiers", "recipes"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation",
                          "-q", "-w", str(tmp_path)], capture_output=True, text=True, timeout=300)
    if out.returncode != 0 and "No module named" in out.stderr and "setuptools" in out.stderr:
        pytest.skip("setuptools is not installed in this environment")
    assert out.returncode == 0, out.stderr
    wheel = next(tmp_path.glob("posttrain-*.whl"))
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
