"""The params files as a whole: their sections, :class:`Settings` and the entry points.

:func:`validate_params` checks a loaded mapping (every problem in one
:class:`~femcal.errors.ConfigError`, each with its line in the file), :func:`load_settings`
reads a complete file into the typed :class:`Settings`, and :func:`describe_setting` gives
the one-line doc of a key.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from femcal.errors import ConfigError
from femcal.settings._messages import BAD, Context, Index, closest, unknown_message
from femcal.settings._validate import Section, settings_of
from femcal.settings.fe import AdaptSettings, CohortSettings, FeSettings, ValidateSettings
from femcal.settings.keywords import SOLVER_SETTINGS, SOLVERS
from femcal.settings.root import (
    BaselinesSettings,
    CalibrateSettings,
    DataSettings,
    DiagnoseSettings,
    EffectsSettings,
    InterpolationSettings,
    InverseSettings,
    MlflowSettings,
    MomentSettings,
    PlantSettings,
    TrainSettings,
)

#: The file kinds: the root pipeline's params.yaml and the FE pipeline's fe/params.yaml.
SCHEMAS: tuple[str, ...] = ("root", "fe")

# Where a section may appear: file kind -> required in a complete file of that kind.
_BOTH = {"root": True, "fe": True}  # required in both files
_ROOT = {"root": True, "fe": False}  # required in params.yaml, allowed in fe/params.yaml
_OPTIONAL = {"root": False, "fe": False}  # allowed in both, required in neither
_FE = {"fe": True}  # fe/params.yaml only
_FE_OPTIONAL = {"fe": False}  # allowed in fe/params.yaml only, not required

#: Sections of each file kind: section -> (class, required in a complete file).
_SECTIONS: dict[str, tuple[type, dict[str, bool]]] = {
    "data": (DataSettings, _BOTH),
    "mlflow": (MlflowSettings, _BOTH),
    "train": (TrainSettings, _BOTH),
    "baselines": (BaselinesSettings, _ROOT),
    "interpolation": (InterpolationSettings, _ROOT),
    "inverse": (InverseSettings, _ROOT),
    "moments": (MomentSettings, _BOTH),
    "effects": (EffectsSettings, _OPTIONAL),
    "calibrate": (CalibrateSettings, _BOTH),
    "plant": (PlantSettings, _ROOT),
    "diagnose": (DiagnoseSettings, _ROOT),
    "fe": (FeSettings, _FE),
    "validate": (ValidateSettings, _FE),
    "adapt": (AdaptSettings, _FE_OPTIONAL),
    "cohort": (CohortSettings, _FE_OPTIONAL),
}


@dataclass(frozen=True)
class Settings:
    """A validated params file: one typed section each (None when the file lacks it).

    Attributes
    ----------
    path : Path
        The file.
    schema : {"root", "fe"}
        The pipeline it drives: the root ``params.yaml`` or the FE pipeline's
        ``fe/params.yaml`` (which also has ``fe`` and ``validate``).
    """

    path: Path
    schema: str
    data: DataSettings | None = None
    mlflow: MlflowSettings | None = None
    train: TrainSettings | None = None
    baselines: BaselinesSettings | None = None
    interpolation: InterpolationSettings | None = None
    inverse: InverseSettings | None = None
    moments: MomentSettings | None = None
    effects: EffectsSettings | None = None
    calibrate: CalibrateSettings | None = None
    plant: PlantSettings | None = None
    diagnose: DiagnoseSettings | None = None
    fe: FeSettings | None = None
    validate: ValidateSettings | None = None
    adapt: AdaptSettings | None = None
    cohort: CohortSettings | None = None


# ====================================================================== validation entry points
def detect_schema(data: Mapping[str, Any]) -> str:
    """``"fe"`` for a file with an ``fe`` or ``validate`` section (fe/params.yaml), else root."""
    return "fe" if "fe" in data or "validate" in data else "root"


def _validate_top(data: Mapping[str, Any], schema: str, ctx: Context) -> dict[str, Any]:
    allowed = {name for name, (_, req) in _SECTIONS.items() if schema in req}
    required = [name for name, (_, req) in _SECTIONS.items() if req.get(schema)]
    missing = [name for name in required if name not in data]
    out: dict[str, Any] = {}
    paired: set[str] = set()
    for key, value in data.items():
        if key == "_path":
            continue
        if key in allowed:
            out[key] = ctx.check(Section(_SECTIONS[key][0]), value, (key,))
            continue
        if key in _SECTIONS:  # fe or validate in a root params file
            ctx.report_at(
                (key,),
                f"not a section of the root params.yaml; {key} belongs to the FE "
                "pipeline's fe/params.yaml",
            )
            continue
        close = closest(str(key), allowed)
        if close in missing:
            paired.add(close)
        ctx.report(
            (key,), unknown_message(key, (), sorted(allowed), {}, missing, "unknown section")
        )
    if ctx.complete:
        for name in missing:
            if name not in paired:
                ctx.report_at(
                    (name,),
                    "missing section; add it (see the project's "
                    f"{'fe/params.yaml' if schema == 'fe' else 'params.yaml'})",
                )
    # The adapter's settings depend on the solver: checked once both are known.
    fe = data.get("fe") if "fe" in allowed else None
    if isinstance(fe, Mapping) and isinstance(fe.get("settings"), Mapping):
        solver = fe.get("solver", SOLVERS[0])
        if solver in SOLVER_SETTINGS:
            checked = ctx.check(SOLVER_SETTINGS[solver], fe["settings"], ("fe", "settings"))
            if isinstance(out.get("fe"), FeSettings) and checked is not BAD:
                out["fe"] = dataclasses.replace(out["fe"], settings=checked)
    return out


def _line_numbers(text: str) -> Callable[[tuple], int | None]:
    """A function path -> 1-based line of that key in the YAML ``text`` (None if unknown)."""
    import yaml

    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:  # pragma: no cover - the text was loaded before
        root = None

    def line(path: tuple) -> int | None:
        node, found = root, None
        for key in path:
            if isinstance(node, yaml.MappingNode):
                for k, v in node.value:
                    if k.value == str(key):
                        found, node = k.start_mark.line + 1, v
                        break
                else:
                    return found
            elif isinstance(node, yaml.SequenceNode) and isinstance(key, Index):
                if int(key) >= len(node.value):
                    return found
                node = node.value[int(key)]
                found = node.start_mark.line + 1
            else:
                return found
        return found

    return line


def _sentence(message: str) -> str:
    return message if message.endswith((".", "?", "!")) else message + "."


def _raise(ctx: Context, where: str, text: str | None) -> None:
    """One ConfigError for every recorded problem, each with its line in the file."""
    if not ctx.problems:
        return
    line_of = _line_numbers(text) if text is not None else (lambda path: None)
    lines = []
    for path, message in ctx.problems:
        hint = next((h for p, h in ctx.hints.items() if path[: len(p)] == p), None)
        if hint and hint not in message:
            message = f"{message}; {hint}"
        lines.append((line_of(path), _sentence(message)))
    lines.sort(key=lambda lm: (lm[0] is None, lm[0] or 0))
    if len(lines) == 1:
        line, message = lines[0]
        raise ConfigError(f"{where}{f', line {line}' if line else ''}: {message}")
    body = "\n".join(f"  {f'line {line}: ' if line else ''}{message}" for line, message in lines)
    raise ConfigError(f"{where}: {len(lines)} invalid settings; fix each and rerun:\n{body}")


def validate_params(
    data: Mapping[str, Any],
    *,
    path: str | Path = "params.yaml",
    schema: str | None = None,
    complete: bool = False,
    text: str | None = None,
) -> Settings | None:
    """Validate a loaded params mapping; raise one ConfigError listing every problem.

    Parameters
    ----------
    data : mapping
        The YAML document (sections at the top).
    path : str or Path
        The file, for messages.
    schema : {"root", "fe"}, optional
        Which file it is (default: :func:`detect_schema`).
    complete : bool
        Require every required section and key (``load_settings``). Otherwise only what the
        file holds is checked, and a command reports a missing key when it reads it.
    text : str, optional
        The file's text, for line numbers in messages.

    Returns
    -------
    Settings or None
        The typed settings when ``complete`` (or when nothing is missing), else None.

    Raises
    ------
    ConfigError
        Unknown, retired, missing (``complete``), mistyped or out-of-range settings.
    """
    schema = schema or detect_schema(data)
    if schema not in SCHEMAS:
        raise ConfigError(f"schema must be one of {', '.join(SCHEMAS)}; got {schema!r}.")
    ctx = Context(complete=complete)
    sections = _validate_top(data, schema, ctx)
    _raise(ctx, str(path), text)
    if any(v is BAD for v in sections.values()):  # incomplete: partial validation only
        return None
    return Settings(path=Path(path), schema=schema, **sections)


def load_settings(path: str | Path = "params.yaml", *, schema: str | None = None) -> Settings:
    """Read, validate and type a complete params file.

    Parameters
    ----------
    path : str or Path
        ``params.yaml`` or ``fe/params.yaml``.
    schema : {"root", "fe"}, optional
        Which file it is (default: ``"fe"`` when it has an ``fe`` section).

    Returns
    -------
    Settings

    Raises
    ------
    ConfigError
        The file is missing or not YAML, or a setting is unknown, retired, missing, of the
        wrong type or out of range (all of them in one message).
    """
    from femcal.config import read_yaml_mapping

    data, text = read_yaml_mapping(path)
    settings = validate_params(data, path=path, schema=schema, complete=True, text=text)
    assert settings is not None  # complete validation returns the settings or raises
    return settings


def describe_setting(keys: Iterable[str]) -> str | None:
    """The one-line doc of the setting at ``keys`` (e.g. ``("calibrate", "max_plots")``)."""
    keys = list(keys)
    if not keys or keys[0] not in _SECTIONS:
        return None
    cls: Any = _SECTIONS[keys[0]][0]
    doc = re.sub(r"^``[^`]+``: ", "", cls.__doc__.splitlines()[0]).rstrip(".")
    for key in keys[1:]:
        specs = settings_of(cls) if dataclasses.is_dataclass(cls) else {}
        if key not in specs:
            return None
        doc = specs[key].metadata["doc"]
        check = specs[key].metadata["check"]
        cls = check.cls if isinstance(check, Section) else None
    return doc
