"""What a wheel carries and what a user of it can run: the licence, the sample's credit, py.typed,
the sample itself, and the README's first command from outside the source tree."""

import json
import re
import subprocess
import sys
from pathlib import Path

from nanogs_warp.data import sample_path
from nanogs_warp.io.ply import load_ply

ROOT = Path(__file__).resolve().parent.parent
PYPROJECT = (ROOT / "pyproject.toml").read_text(encoding="utf-8")


def test_licence_is_the_full_apache_2_text():
    text = (ROOT / "LICENSE").read_text(encoding="utf-8")
    assert "Apache License" in text and "Version 2.0, January 2004" in text
    assert "TERMS AND CONDITIONS FOR USE, REPRODUCTION, AND DISTRIBUTION" in text
    assert "END OF TERMS AND CONDITIONS" in text and len(text.splitlines()) > 190
    assert re.search(r'^license = "Apache-2.0"$', PYPROJECT, flags=re.MULTILINE)
    assert re.search(r'^license-files = \["LICENSE"\]$', PYPROJECT, flags=re.MULTILINE)


def test_package_data_ships_the_sample_its_credit_and_py_typed():
    assert '"nanogs_warp" = ["py.typed"]' in PYPROJECT
    assert '"nanogs_warp.data" = ["*.ply", "CREDITS.md"]' in PYPROJECT
    assert '"nanogs_warp.compiled" = ["*/*.tar.xz"]' in PYPROJECT  # the shipped kernels (shipped_kernels.py)
    package = ROOT / "nanogs_warp"
    assert (package / "py.typed").is_file()
    credits = (package / "data" / "CREDITS.md").read_text(encoding="utf-8")
    assert "Marcel Padilla" in credits and "CC-BY-4.0" in credits and "Changes:" in credits
    assert sample_path().name == "plant_crop.ply" and sample_path().is_file()
    assert load_ply(sample_path()).count == 20_000


def test_project_metadata():
    for field in ("authors = ", "classifiers = [", "keywords = "):
        assert field in PYPROJECT
    assert '"Typing :: Typed"' in PYPROJECT and '"warp-lang>=1.19,<1.20"' in PYPROJECT


def test_readme_first_command_runs_outside_the_source_tree(tmp_path):
    """The README's first command, ``pip install . && nanogs-warp simplify --sample ...``: the part
    after the install, run from an empty folder through the installed package."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    first = re.search(r"```bash\n(.*?)\n```", readme, flags=re.DOTALL).group(1).strip()
    install, _, command = first.partition(" && ")
    assert install == "pip install ."
    words = command.split()
    assert words[:3] == ["nanogs-warp", "simplify", "--sample"]
    done = subprocess.run(
        [sys.executable, "-m", "nanogs_warp", *words[1:], "--device", "cpu", "--json"],
        cwd=tmp_path, capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["input"] == str(sample_path().resolve())
    written = sorted(p.name for p in tmp_path.iterdir())
    assert written == sorted(Path(o["path"]).name for o in summary["outputs"]) and len(written) == 3
    assert [o["count"] for o in summary["outputs"]] == [2000, 200, 20]


def test_the_wheel_lists_every_subpackage():
    """setuptools is given the packages by name: each folder of the package with an __init__.py,
    the kernels folder as nanogs_warp.kernels, and the shipped compiled kernels' folder (data
    only, nanogs_warp.compiled), so that none is missing from a wheel."""
    import tomllib

    listed = set(tomllib.loads(PYPROJECT)["tool"]["setuptools"]["packages"])
    package = ROOT / "nanogs_warp"
    folders = {".".join(("nanogs_warp", *p.parent.relative_to(package).parts)) for p in package.rglob("__init__.py")}
    assert {"nanogs_warp.io", "nanogs_warp.eval", "nanogs_warp.refinement", "nanogs_warp.batch", "nanogs_warp.cli"} <= folders
    assert listed == folders | {"nanogs_warp.kernels", "nanogs_warp.compiled"}


def test_the_console_script_and_python_m_run_the_command():
    import importlib
    import tomllib

    target = tomllib.loads(PYPROJECT)["project"]["scripts"]["nanogs-warp"]
    module, _, name = target.partition(":")
    assert callable(getattr(importlib.import_module(module), name))
    done = subprocess.run([sys.executable, "-m", "nanogs_warp", "--version"], capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip() == "nanogs-warp 0.1.0" and done.stderr == ""


def test_the_readme_explains_the_warp_pin_the_package_has():
    """The README's note on the warp-lang pin names the pin in pyproject.toml and how it moves."""
    import tomllib

    pin = next(d for d in tomllib.loads(PYPROJECT)["project"]["dependencies"] if d.startswith("warp-lang"))
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = re.search(r"^## The warp-lang pin\n(.*?)(?=^## |\Z)", readme, flags=re.MULTILINE | re.DOTALL)
    assert section is not None
    assert f"`{pin}`" in section.group(1) and "one minor version at a time" in section.group(1)
