"""Packaging: every imported package is declared, constraints.txt pins them, the licence."""

from __future__ import annotations

import ast
import re
import sys
from importlib import metadata
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirement_name(requirement: str) -> str:
    """The distribution a PEP 508 requirement names (``torch==2.13.0`` -> ``torch``)."""
    return _canonical(re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", requirement).group(1))


def _imported_top_level(folders: list[Path]) -> dict[str, list[str]]:
    """Top-level module names imported (absolutely) anywhere under ``folders`` -> the files."""
    found: dict[str, list[str]] = {}
    for path in sorted(p for folder in folders for p in folder.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split(".")[0], []).append(str(path.relative_to(ROOT)))
    return found


def _undeclared(folders: list[Path], declared: set[str], local: set[str]) -> dict[str, str]:
    """Third-party imports of ``folders`` whose distribution is not in ``declared``."""
    dists = metadata.packages_distributions()
    problems = {}
    for module, files in _imported_top_level(folders).items():
        if module in sys.stdlib_module_names or module in local or module == "__future__":
            continue
        owners = {_canonical(d) for d in dists.get(module, [])}
        if not owners & declared:
            problems[module] = f"distribution {sorted(owners) or '?'} (imported in {files[0]})"
    return problems


def test_every_package_src_imports_is_a_dependency():
    declared = {_requirement_name(r) for r in PYPROJECT["dependencies"]}
    assert _undeclared([ROOT / "src"], declared, local={"femcal"}) == {}


def test_every_package_tests_and_experiments_import_is_declared():
    declared = {
        _requirement_name(r)
        for r in [*PYPROJECT["dependencies"], *PYPROJECT["optional-dependencies"]["dev"]]
    }
    folders = [ROOT / "tests", ROOT / "experiments"]
    local = {"femcal", "experiments"} | {p.stem for f in folders for p in f.rglob("*.py")}
    assert _undeclared(folders, declared, local) == {}


def _constraints() -> dict[str, str]:
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        name, sep, version = line.partition("==")
        assert sep and version, f"constraints.txt: {line!r} is not an exact pin (name==version)"
        pins[_canonical(name)] = version
    return pins


def test_constraints_pin_every_dependency_and_the_cpu_torch():
    pins = _constraints()
    required = [*PYPROJECT["dependencies"], *PYPROJECT["optional-dependencies"]["dev"]]
    missing = [r for r in required if _requirement_name(r) not in pins]
    assert missing == [], "run `make lock` after installing them"
    # torch: exactly pyproject's version, never a local label (+cpu) nor CUDA packages,
    # which a torch from the package index would pull in (gigabytes).
    assert "torch==2.13.0" in PYPROJECT["dependencies"]
    assert pins["torch"] == "2.13.0"
    assert not [n for n in pins if n.startswith(("nvidia-", "triton", "cuda"))]
    assert "femcal" not in pins


def test_make_install_uses_the_constraints():
    makefile = (ROOT / "Makefile").read_text()
    assert re.search(r"^\$\(VENV\)/\.installed: .*constraints\.txt", makefile, re.M)
    assert 'pip install --quiet -c constraints.txt -e ".[dev]"' in makefile
    assert re.search(r"^lock:", makefile, re.M)
    assert "make lint" in (ROOT / ".ci" / "run").read_text()


def test_licence_is_mit():
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License")
    assert "Copyright (c) 2026 the femcal developers" in text
    assert PYPROJECT["license"] == "MIT"


def test_the_default_run_leaves_the_slow_tests_to_their_own_ci_step():
    """`make test` excludes the slow tests and shares the rest over one process per core;
    every test module that runs `dvc repro` is slow; CI runs the slow ones as a step of their
    own (`make test-slow`)."""
    pytest_config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]
    assert "-m 'not slow'" in pytest_config["ini_options"]["addopts"]
    repro = [p for p in (ROOT / "tests").rglob("test_*.py") if '"repro"' in p.read_text()]
    assert repro, "no test runs dvc repro any more: update this test"
    unmarked = [p.name for p in repro if "pytest.mark.slow" not in p.read_text()]
    assert unmarked == []
    makefile = (ROOT / "Makefile").read_text()
    parallel = r"^test:.*\n\tOMP_NUM_THREADS=1 pytest -n auto --dist loadfile "
    assert re.search(parallel, makefile, re.M)
    assert re.search(r"^test-slow:.*\n\tpytest -m slow", makefile, re.M)
    assert "make test-slow" in (ROOT / ".ci" / "run").read_text()
