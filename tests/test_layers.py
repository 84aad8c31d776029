"""The layers hold (docs/architecture.md): import-linter's contract in pyproject.toml, function-level
imports included, over the whole source tree."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_imports_only_the_layers_below_it():
    lint = Path(sys.executable).with_name("lint-imports")
    run = subprocess.run([str(lint), "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and "1 kept, 0 broken" in run.stdout, run.stdout[-3000:] + run.stderr[-2000:]


def test_every_module_is_named_in_the_architecture_map():
    """docs/architecture.md's folder table is where a newcomer looks a module up: a module added without a
    line there (eleven had been, by 2026-12-05) is missing from the map."""
    import re

    architecture = (ROOT / "docs" / "architecture.md").read_text()
    named = set(re.findall(r"`([A-Za-z_/]+)(?:\.py)?[`*( ]", architecture)) | set(re.findall(r"([A-Za-z_]+)\.py", architecture))
    packages = ["schemas", "warehouse", "envs", "policies", "stages", "flows", "dashboards", "bench"]
    modules = [path for package in packages for path in (ROOT / package).rglob("*.py")
               if path.stem not in ("__init__", "__main__") and ".venv" not in path.parts]
    unnamed = sorted(str(path.relative_to(ROOT)) for path in modules if path.stem not in named)
    assert not unnamed, f"modules docs/architecture.md's folder table does not name: {unnamed}"
