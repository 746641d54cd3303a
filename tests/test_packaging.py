"""The distribution ships every package of the tree: a folder left out of pyproject.toml would
vanish from a non-editable install (Docker, a wheel) while every test here still passed."""

from __future__ import annotations

import tomllib

from .conftest import REPO_ROOT

ROOTS = {"pipeline": "robonav.pipeline", "services": "robonav.services", "calibration": "robonav.calibration",
         "configs": "robonav.configs"}


def _declared() -> tuple[set[str], dict[str, str]]:
    setuptools = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]
    return set(setuptools["packages"]), setuptools["package-dir"]


def test_every_folder_with_python_code_is_a_declared_package() -> None:
    declared, _ = _declared()
    found = set()
    for folder, package in ROOTS.items():
        for source in (REPO_ROOT / folder).rglob("*.py"):
            relative = source.parent.relative_to(REPO_ROOT / folder)
            assert (source.parent / "__init__.py").is_file(), f"{source.parent} holds Python code but no __init__.py"
            found.add(".".join([package, *relative.parts]))
    assert found - declared == set(), "packages missing from pyproject.toml [tool.setuptools] packages"
    assert declared - found == set(), "pyproject.toml declares packages that do not exist"


def test_package_dirs_map_the_four_roots() -> None:
    _, package_dir = _declared()
    assert package_dir == {package: folder for folder, package in ROOTS.items()}


MAX_MODULE_LINES = 500
LONG_BY_DESIGN = {"pipeline/wire/messages.py"}  # one class per wire message, kept in one place


def test_modules_stay_one_concept_long() -> None:
    long = {str(source.relative_to(REPO_ROOT)): n for folder in ("pipeline", "services", "calibration")
            for source in (REPO_ROOT / folder).rglob("*.py")
            if (n := len(source.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES}
    assert set(long) <= LONG_BY_DESIGN, f"modules over {MAX_MODULE_LINES} lines: split them by concept: {long}"
