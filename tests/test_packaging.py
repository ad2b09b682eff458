"""A non-editable install ships every package, the recipes and the verifier examples."""
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_wheel_contains_every_package_and_recipe(tmp_path):
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--no-build-isolation",
                          "-q", "-w", str(tmp_path)], capture_output=True, text=True, timeout=300)
    if out.returncode != 0 and "No module named" in out.stderr and "setuptools" in out.stderr:
        pytest.skip("setuptools is not installed in this environment")
    assert out.returncode == 0, out.stderr
    wheel = next(tmp_path.glob("posttrain-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    for top in ("posttrain", "verifiers"):
        for init in (ROOT / top).rglob("*.py"):
            rel = init.relative_to(ROOT).as_posix()
            assert rel in names, f"{rel} is not in the wheel: add its package to [tool.setuptools] packages"
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
