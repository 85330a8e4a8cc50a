"""Size limits of src/femcal: modules, functions and public signatures.

* every module is at most ``MAX_MODULE_LINES`` lines;
* every function or method, nested ones included, spans at most ``MAX_FUNCTION_LINES`` lines
  (``end_lineno - lineno + 1`` of the ``def``; decorators not counted);
* every public function or method takes at most ``MAX_PUBLIC_PARAMETERS`` parameters
  (``self``/``cls``, ``*args`` and ``**kwargs`` not counted; keyword-only ones counted).
  Public: no component of the module path and no component of the qualified name starts
  with ``_``, and the function is not defined inside another function.

Known exceptions live in one dict per check, keyed ``"src/femcal/<path>.py:<qualified name>"``
(``"src/femcal/<path>.py"`` for modules), each with a one-line reason. An entry that no longer
offends fails its own test, so the lists only shrink.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "src" / "femcal"

MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 120
MAX_PUBLIC_PARAMETERS = 10

#: Modules over MAX_MODULE_LINES: "src/femcal/<path>.py" -> why.
ALLOWED_LONG_MODULES: dict[str, str] = {}

#: Functions over MAX_FUNCTION_LINES: "src/femcal/<path>.py:<qualified name>" -> why.
ALLOWED_LONG_FUNCTIONS: dict[str, str] = {}

#: Public functions over MAX_PUBLIC_PARAMETERS: "src/femcal/<path>.py:<qualified name>" -> why.
ALLOWED_MANY_PARAMETERS: dict[str, str] = {}


@dataclass(frozen=True)
class Function:
    path: str  # relative to the repository root, e.g. "src/femcal/cli.py"
    line: int
    qualname: str  # "outer.inner", "Class.method"
    lines: int
    parameters: int
    public: bool

    @property
    def key(self) -> str:
        return f"{self.path}:{self.qualname}"


def _modules() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def _relative(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def _parameter_count(node: ast.FunctionDef | ast.AsyncFunctionDef, in_class: bool) -> int:
    args = node.args
    positional = [*args.posonlyargs, *args.args]
    if in_class and positional and positional[0].arg in ("self", "cls"):
        positional = positional[1:]
    return len(positional) + len(args.kwonlyargs)


def _collect(path: Path) -> list[Function]:
    relative = _relative(path)
    public_module = not any(part.startswith("_") for part in path.relative_to(PACKAGE).parts)
    found: list[Function] = []

    def visit(node: ast.AST, prefix: str, public_scope: bool, in_class: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                qualname = f"{prefix}{child.name}"
                found.append(
                    Function(
                        path=relative,
                        line=child.lineno,
                        qualname=qualname,
                        lines=child.end_lineno - child.lineno + 1,
                        parameters=_parameter_count(child, in_class),
                        public=public_scope and not child.name.startswith("_"),
                    )
                )
                visit(child, f"{qualname}.", public_scope=False, in_class=False)
            elif isinstance(child, ast.ClassDef):
                visit(
                    child,
                    f"{prefix}{child.name}.",
                    public_scope=public_scope and not child.name.startswith("_"),
                    in_class=True,
                )
            else:
                visit(child, prefix, public_scope, in_class)

    visit(ast.parse(path.read_text(), filename=relative), "", public_module, in_class=False)
    return found


@cache
def _functions() -> tuple[Function, ...]:
    return tuple(function for path in _modules() for function in _collect(path))


def _check(
    offenders: list[tuple[str, str]], allowed: dict[str, str], name: str, limit: str
) -> None:
    """Fail listing every offender not in ``allowed`` and every stale entry of ``allowed``.

    ``offenders`` holds (key, report line ``path:line name (N unit)``) pairs.
    """
    new = sorted(line for key, line in offenders if key not in allowed)
    offending = {key for key, _ in offenders}
    stale = sorted(key for key in allowed if key not in offending)
    problems = []
    if new:
        problems.append(
            f"{len(new)} over the limit ({limit}); split them, or add them to {name} "
            "with a one-line reason:\n  " + "\n  ".join(new)
        )
    if stale:
        problems.append(
            f"stale entries of {name}, within the limit now; "
            f"remove them from {name}:\n  " + "\n  ".join(stale)
        )
    assert not problems, "\n".join(problems)


def test_modules_are_short() -> None:
    offenders = []
    for path in _modules():
        relative = _relative(path)
        lines = len(path.read_text().splitlines())
        if lines > MAX_MODULE_LINES:
            offenders.append((relative, f"{relative}:1 {path.stem} ({lines} lines)"))
    _check(offenders, ALLOWED_LONG_MODULES, "ALLOWED_LONG_MODULES", f"{MAX_MODULE_LINES} lines")


def test_functions_are_short() -> None:
    offenders = [
        (f.key, f"{f.path}:{f.line} {f.qualname} ({f.lines} lines)")
        for f in _functions()
        if f.lines > MAX_FUNCTION_LINES
    ]
    _check(
        offenders,
        ALLOWED_LONG_FUNCTIONS,
        "ALLOWED_LONG_FUNCTIONS",
        f"{MAX_FUNCTION_LINES} lines",
    )


def test_public_signatures_are_short() -> None:
    offenders = [
        (f.key, f"{f.path}:{f.line} {f.qualname} ({f.parameters} parameters)")
        for f in _functions()
        if f.public and f.parameters > MAX_PUBLIC_PARAMETERS
    ]
    _check(
        offenders,
        ALLOWED_MANY_PARAMETERS,
        "ALLOWED_MANY_PARAMETERS",
        f"{MAX_PUBLIC_PARAMETERS} parameters; use an options object",
    )
