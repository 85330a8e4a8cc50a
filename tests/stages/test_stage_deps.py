"""Every module a DVC stage runs is among that stage's deps, so editing it reruns the stage.

A stage's command is ``femcal <command>``: :mod:`femcal.cli` dispatches to the stage's module
(:data:`femcal.stages.COMMANDS`). Their imports are followed through the source (``ast``;
imports inside functions count, ``if TYPE_CHECKING:`` blocks do not), and every femcal module
reached must lie under a dep path of the stage: a file covers itself, a folder its files. A
subpackage reached is listed as its folder, since its registry imports plugin modules by name
(``femcal.surrogates.*``, ``femcal.effects.*``, ...), which no import statement shows.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import yaml

from femcal.stages import COMMANDS

ROOT = Path(__file__).resolve().parents[2]
SRC = ROOT / "src"
PIPELINES = (ROOT / "dvc.yaml", ROOT / "fe" / "dvc.yaml")


def module_file(name: str) -> Path | None:
    """The source file of a femcal module or package, or None (a name, not a module)."""
    path = SRC.joinpath(*name.split("."))
    if (path / "__init__.py").exists():
        return path / "__init__.py"
    if path.with_suffix(".py").exists():
        return path.with_suffix(".py")
    return None


def imported_modules(path: Path, name: str) -> set[str]:
    """The femcal modules one file imports (``from m import x`` counts ``m.x`` if a module)."""
    tree = ast.parse(path.read_text())
    skipped = {
        id(n)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
        for n in ast.walk(node)
    }
    found: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.split(".")[0] == "femcal"}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")[: -1 if path.name != "__init__.py" else None]
                base = base[: len(base) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            if module.split(".")[0] != "femcal":
                continue
            found.add(module)
            found |= {f"{module}.{a.name}" for a in node.names if module_file(f"{module}.{a.name}")}
    return found


def closure(*starts: str) -> set[Path]:
    """Source files of every femcal module reached from ``starts`` (package inits included)."""
    seen: set[str] = set()
    todo = list(starts)
    while todo:
        name = todo.pop()
        path = module_file(name)
        if name in seen or path is None:
            continue
        seen.add(name)
        parts = name.split(".")
        todo += [".".join(parts[:i]) for i in range(1, len(parts))]
        todo += imported_modules(path, name)
    return {module_file(n) for n in seen}


def stages() -> list[tuple[str, str, list[str], Path]]:
    """(pipeline, stage, deps, module) for every command of every stage of both pipelines."""
    out = []
    for pipeline in PIPELINES:
        for stage, spec in yaml.safe_load(pipeline.read_text())["stages"].items():
            body = spec.get("do", spec)
            cmds = body["cmd"] if isinstance(body["cmd"], list) else [body["cmd"]]
            for cmd in cmds:  # a stage may run several commands, each checked
                words = cmd.split()
                while words and "=" in words[0]:  # an environment setting (OMP_NUM_THREADS=1)
                    words = words[1:]
                # ``femcal <command>``, or ``python -m femcal.<module>`` (a library module's main)
                command = words[2] if words[:2] == ["python", "-m"] else words[1]
                out.append((pipeline.relative_to(ROOT).as_posix(), stage, body["deps"], command))
    return out


@pytest.mark.parametrize(
    ("pipeline", "stage", "deps", "command"),
    stages(),
    ids=[f"{p}:{s}:{c}" for p, s, _, c in stages()],
)
def test_every_module_a_stage_runs_is_a_dep(pipeline, stage, deps, command):
    folder = (ROOT / pipeline).parent
    covered = [(folder / d).resolve() for d in deps if "${" not in d]
    if command.startswith("femcal."):
        assert module_file(command), f"{pipeline}: stage {stage} runs an unknown module {command}"
        files = closure(command)
    else:
        assert command in COMMANDS, f"{pipeline}: stage {stage} runs an unknown command {command!r}"
        files = closure("femcal.cli", f"femcal.stages.{COMMANDS[command]}")
    missing = sorted(
        f.relative_to(ROOT).as_posix()
        for f in files
        if not any(f == c or c in f.parents for c in covered)
    )
    assert not missing, (
        f"{pipeline}: stage {stage} (femcal {command}) runs these modules, which are not in its "
        f"deps: {missing}. Add them to deps in {pipeline} (a subpackage as its folder), so that "
        "editing them reruns the stage."
    )


def test_the_closure_follows_imports_inside_functions():
    """The check can fail: the calibrate stage reaches the calibrators through a function-level
    import, and its closure holds them; fetch's does not."""
    calibrate = closure("femcal.stages.calibrate")
    assert SRC / "femcal" / "calibration" / "base.py" in calibrate
    assert SRC / "femcal" / "calibration" / "base.py" not in closure("femcal.stages.fetch")
