"""femcal's import graph: the library never reaches up to its command line, and has no cycle.

The graph is read from the source with ``ast`` (nothing is imported). Its nodes are the
modules under ``src/femcal`` (a package is its ``__init__.py``); an edge ``a -> b`` is an
import statement in ``a`` that names ``b``:

- ``import femcal.x.y`` names ``femcal.x.y``; ``from femcal.x import y`` names ``femcal.x``, and
  ``femcal.x.y`` too where ``y`` is a module; relative imports are resolved;
- importing ``femcal.x.y`` also runs the package ``femcal.x`` first: an edge to each package on
  the way, except the packages that hold ``a`` itself (they are already being imported, and
  the root ``femcal`` holds every module).

What each rule counts:

*the command line*
    :data:`COMMAND_LINE` (``femcal.stages`` and below, ``femcal.cli``, ``femcal.__main__``);
    every other module is *library*. A library module may not import the command line in any
    import statement at all: at module level, inside a function, or under
    ``if TYPE_CHECKING:``. Nor may it run femcal's command line as a program: a list or tuple
    of literal strings with ``"femcal"`` as an item, or ``"-m"`` followed by ``"femcal..."``
    (a subprocess's arguments), counts as running it, and so does a string ``"... -m femcal..."``
    or ``"femcal ..."`` given to ``subprocess``'s or ``os``' functions that run a program
    (:data:`PROGRAM_RUNNERS`).
*cycles*
    Only the imports that run when the module is imported count: those at module level
    (in ``try``/``if``/``with`` blocks too). Imports inside a function or lambda body, and
    imports under ``if TYPE_CHECKING:``, are left out: they run later or never. A cycle is a
    strongly connected set of two modules or more; :data:`KNOWN_CYCLES` lists none.
"""

from __future__ import annotations

import ast
import re
from functools import cache
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "femcal"

#: The command line: these modules and everything below them.
COMMAND_LINE = ("femcal.stages", "femcal.cli", "femcal.__main__")

#: Import cycles accepted for now, each a sorted tuple of modules with the reason. Empty: the
#: module-level graph has no cycle. A cycle added here needs a one-line reason.
KNOWN_CYCLES: dict[tuple[str, ...], str] = {}


def module_name(path: Path) -> str:
    """``src/femcal/a/b.py`` -> ``femcal.a.b``; ``src/femcal/a/__init__.py`` -> ``femcal.a``."""
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def modules() -> dict[str, Path]:
    """Every femcal module, by name."""
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def is_command_line(name: str) -> bool:
    return any(name == c or name.startswith(c + ".") for c in COMMAND_LINE)


def _target(name: str, path: Path, node: ast.ImportFrom) -> str:
    """The module a ``from ... import`` names, relative imports resolved."""
    if not node.level:
        return node.module or ""
    base = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    base = base[: len(base) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


@cache
def imports(name: str) -> tuple[tuple[str, int, bool], ...]:
    """``(imported module, line, runs on import)`` for each femcal module ``name`` names.

    ``runs on import`` is False inside a function or lambda and under ``if TYPE_CHECKING:``.
    """
    path = modules()[name]
    found: list[tuple[str, int, bool]] = []

    def visit(node: ast.AST, runs: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
                visit(child, False)
            elif isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                for stmt in child.body:
                    visit(ast.Module(body=[stmt], type_ignores=[]), False)
                for stmt in child.orelse:
                    visit(ast.Module(body=[stmt], type_ignores=[]), runs)
            elif isinstance(child, ast.Import):
                found.extend(
                    (a.name, child.lineno, runs)
                    for a in child.names
                    if a.name.split(".")[0] == "femcal"
                )
            elif isinstance(child, ast.ImportFrom):
                target = _target(name, path, child)
                if target.split(".")[0] != "femcal":
                    continue
                found.append((target, child.lineno, runs))
                found.extend(
                    (f"{target}.{a.name}", child.lineno, runs)
                    for a in child.names
                    if f"{target}.{a.name}" in modules()
                )
            else:
                visit(child, runs)

    visit(ast.parse(path.read_text(), filename=str(path)), True)
    return tuple(found)


def edges(name: str) -> set[str]:
    """The modules importing ``name`` runs at once (module docstring): each module named and
    each package on its way that does not hold ``name``."""
    out = set()
    for target, _, runs in imports(name):
        if not runs:
            continue
        parts = target.split(".")
        for i in range(2, len(parts) + 1):
            step = ".".join(parts[:i])
            holds_name = name == step or name.startswith(step + ".")
            if step in modules() and not holds_name:
                out.add(step)
    return out


def cycles() -> list[tuple[str, ...]]:
    """The import graph's cycles (:func:`strongly_connected`)."""
    return strongly_connected({name: sorted(edges(name)) for name in modules()})


def strongly_connected(graph: dict[str, list[str]]) -> list[tuple[str, ...]]:
    """The strongly connected sets of two nodes or more of ``graph`` (node -> its targets;
    Tarjan's algorithm without recursion), each sorted, in sorted order."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[tuple[str, ...]] = []
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(graph[start]))]
        index[start] = low[start] = len(index)
        stack.append(start)
        while work:
            node, targets = work[-1]
            for nxt in targets:
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    work.append((nxt, iter(graph[nxt])))
                    break
                if nxt in stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    members = []
                    while True:
                        member = stack.pop()
                        members.append(member)
                        if member == node:
                            break
                    if len(members) > 1:
                        found.append(tuple(sorted(members)))
    return sorted(found)


#: Functions that run a program from a command string (``subprocess.run("...", shell=True)``).
PROGRAM_RUNNERS = (
    *("run", "Popen", "call", "check_call", "check_output", "getoutput", "getstatusoutput"),
    *("system", "popen", "create_subprocess_shell", "create_subprocess_exec"),
)
#: A command string that runs femcal: ``python -m femcal ...`` or ``femcal ...``.
COMMAND_STRING = re.compile(r"(^|\s)-m\s+femcal(\.|\s|$)|^\s*femcal(\s|$)")


def runs_command_line(tree: ast.AST) -> list[int]:
    """Lines that run femcal's command line as a program: a list or tuple literal naming it
    (a subprocess's arguments), or a string naming it given to a function of
    :data:`PROGRAM_RUNNERS`."""
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and ast.unparse(node.func).split(".")[-1] in PROGRAM_RUNNERS:
            texts = [
                c.value
                for arg in (*node.args, *(k.value for k in node.keywords))
                for c in ast.walk(arg)
                if isinstance(c, ast.Constant) and isinstance(c.value, str)
            ]
            if any(COMMAND_STRING.search(t) for t in texts):
                lines.append(node.lineno)
        if not isinstance(node, ast.List | ast.Tuple):
            continue
        words = [e.value for e in node.elts if isinstance(e, ast.Constant)]
        after_m = [b for a, b in zip(words, words[1:]) if a == "-m"]
        if "femcal" in words or any(str(w).split(".")[0] == "femcal" for w in after_m):
            lines.append(node.lineno)
    return sorted(set(lines))


def test_no_library_module_imports_the_command_line():
    upward = [
        f"{modules()[name].relative_to(SRC)}:{line} imports {target}"
        for name in modules()
        if not is_command_line(name)
        for target, line, _ in imports(name)
        if is_command_line(target)
    ]
    assert not upward, (
        "library modules import the command line (femcal.stages, femcal.cli); move what they "
        "need into the library (e.g. femcal.jobs) and have the stage call it:\n  "
        + "\n  ".join(upward)
    )


def test_no_library_module_runs_the_command_line():
    running = [
        f"{path.relative_to(SRC)}:{line}"
        for name, path in modules().items()
        if not is_command_line(name)
        for line in runs_command_line(ast.parse(path.read_text()))
    ]
    assert not running, (
        "library modules run femcal's command line as a program; call the library function "
        "instead (femcal.jobs.calibrate.run_calibration, femcal.jobs.diagnose.run_diagnosis):"
        "\n  " + "\n  ".join(running)
    )


def test_the_import_graph_has_no_cycle_but_the_known_ones():
    found = cycles()
    new = [c for c in found if c not in KNOWN_CYCLES]
    stale = [c for c in KNOWN_CYCLES if c not in found]
    assert not new, (
        "import cycles among module-level imports (an import inside the function that needs "
        "it, or under `if TYPE_CHECKING:` for a type, breaks one):\n  "
        + "\n  ".join(" <-> ".join(c) for c in new)
    )
    assert not stale, f"KNOWN_CYCLES lists cycles that are gone; remove them: {stale}"


def test_the_checks_can_fail():
    """Each rule finds what it looks for: an upward import, a command run, a cycle."""
    assert is_command_line("femcal.stages.calibrate") and is_command_line("femcal.cli")
    assert not is_command_line("femcal.jobs.calibrate")
    tree = ast.parse(
        "import subprocess, sys\n"
        "subprocess.run([sys.executable, '-m', 'femcal', 'calibrate'])\n"
        "subprocess.run(['femcal', 'diagnose'])\n"
        "subprocess.run(['git', 'rev-parse', 'HEAD'])\n"
        "subprocess.run(f'{sys.executable} -m femcal.fe.cohort --out x', shell=True)\n"
        "os.system('femcal diagnose --measurements m.csv')\n"
        "NOTE = 'python -m femcal.fe.hidden --noise-deg'\n"
        "subprocess.run('echo femcalibrate', shell=True)\n"
    )
    assert runs_command_line(tree) == [2, 3, 5, 6]
    # the graph's reader: femcal.jobs.calibrate imports femcal.jobs.common at module level,
    # and the package femcal.jobs holds it (no edge to its own package)
    assert "femcal.jobs.common" in edges("femcal.jobs.calibrate")
    assert "femcal.jobs" not in edges("femcal.jobs.calibrate")
    # a stage imports its library function: an edge from the command line down
    assert "femcal.jobs.calibrate" in edges("femcal.stages.calibrate")
    assert strongly_connected({"a": ["b"], "b": ["c"], "c": ["a", "d"], "d": []}) == [
        ("a", "b", "c")
    ]
    assert strongly_connected({"a": ["b"], "b": []}) == []
    # function-level imports are read but run later: no edge
    assert any(not runs for _, _, runs in imports("femcal.jobs.calibrate"))
    assert "femcal.calibration" not in edges("femcal.jobs.calibrate")


#: Left out of the private-name rule, as importers and as sources: ``femcal.settings`` is
#: rewritten separately (issue 56), and that rewrite settles its module boundaries.
PRIVATE_NAMES_EXEMPT = ("femcal.settings",)


def _exempt(name: str) -> bool:
    return any(name == p or name.startswith(p + ".") for p in PRIVATE_NAMES_EXEMPT)


def private_imports(name: str, tree: ast.AST) -> list[str]:
    """``"<line>: from <module> import <_name>"`` for each private name module ``name`` imports
    from another femcal module (``_x`` but not ``__x__``); relative imports are resolved."""
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.ImportFrom):
            continue
        source = _target(name, modules().get(name, PACKAGE / "x.py"), node)
        if not (source == "femcal" or source.startswith("femcal.")) or _exempt(source):
            continue
        for alias in node.names:
            if alias.name.startswith("_") and not alias.name.startswith("__"):
                found.append(f"{node.lineno}: from {source} import {alias.name}")
    return found


def test_no_module_imports_another_modules_private_names():
    """A name another module imports is part of its module's interface: it has a public name."""
    offenders = [
        f"{path.relative_to(SRC)}:{hit}"
        for name, path in modules().items()
        if not _exempt(name)
        for hit in private_imports(name, ast.parse(path.read_text(encoding="utf-8")))
    ]
    assert not offenders, "private names imported across modules:\n" + "\n".join(offenders)


def test_the_private_name_check_can_fail():
    """The rule finds absolute and relative imports of private names, and not dunder names."""
    tree = ast.parse(
        "from femcal.diagnose.fits import Fit, _hidden\n"
        "from .fits import _relative\n"
        "from femcal import __version__\n"
        "from numpy import _private_elsewhere\n"
    )
    assert private_imports("femcal.diagnose.search", tree) == [
        "1: from femcal.diagnose.fits import _hidden",
        "2: from femcal.diagnose.fits import _relative",
    ]
    assert _exempt("femcal.settings._format") and not _exempt("femcal.settingsx")
