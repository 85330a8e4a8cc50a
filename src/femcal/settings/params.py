"""The params files as a whole: :class:`Settings`, :func:`validate_params` (a loaded mapping;
every problem in one ConfigError), :func:`load_settings` (a complete file)."""

import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, get_args

from pydantic import TypeAdapter, ValidationError

from femcal.errors import ConfigError
from femcal.settings import _format as fmt
from femcal.settings import fe as _fe
from femcal.settings import root as _root

#: The file kinds: the root pipeline's params.yaml and the FE pipeline's fe/params.yaml.
SCHEMAS: tuple[str, ...] = ("root", "fe")
_BOTH, _ROOT, _FE = {"root": True, "fe": True}, {"root": True, "fe": False}, {"fe": True}


def _section(files: dict[str, bool]) -> Any:
    """A section of the file kinds ``files`` (kind -> required in a full file)."""
    return field(default=None, metadata={"files": files})


@dataclass(frozen=True)
class Settings:
    """A validated params file (``path``; ``schema`` "root" or "fe"): one typed section each,
    None when the file lacks it or, checked partially, the section misses required keys
    (``partial``: section -> those it gives, validated; :meth:`require`). ``given``: section
    -> the keys the file gives it."""

    path: Path
    schema: str
    given: dict[str, tuple[str, ...]] = field(default_factory=dict)
    partial: dict[str, Any] = field(default_factory=dict, repr=False)
    data: _root.DataSettings | None = _section(_BOTH)
    mlflow: _root.MlflowSettings | None = _section(_BOTH)
    train: _root.TrainSettings | None = _section(_BOTH)
    baselines: _root.BaselinesSettings | None = _section(_ROOT)
    interpolation: _root.InterpolationSettings | None = _section(_ROOT)
    inverse: _root.InverseSettings | None = _section(_ROOT)
    moments: _root.MomentSettings | None = _section(_BOTH)
    effects: _root.EffectsSettings | None = _section({"root": False, "fe": False})
    calibrate: _root.CalibrateSettings | None = _section(_BOTH)
    plant: _root.PlantSettings | None = _section(_ROOT)
    diagnose: _root.DiagnoseSettings | None = _section(_ROOT)
    fe: _fe.FeSettings | None = _section(_FE)
    validate: _fe.ValidateSettings | None = _section(_FE)
    adapt: _fe.AdaptSettings | None = _section({"fe": False})
    cohort: _fe.CohortSettings | None = _section({"fe": False})

    def require(self, name: str, *keys: str) -> Any:
        """Section ``name``, which must give ``keys``; a partial section serves the keys it
        gives (reading a missing one raises the ConfigError naming it, as does an absent
        section or a missing key of ``keys`` here)."""
        value = getattr(self, name) or self.partial.get(name)
        missing = [k for k in keys if k not in self.given.get(name, ())]
        if value is not None and not missing:
            return value
        raise missing_setting(self.path, f"{name}.{missing[0]}" if missing else name)


#: The sections of each file kind: section -> (model, file kind -> required in a full file).
SECTIONS: dict[str, tuple[type, dict[str, bool]]] = {
    f.name: (get_args(f.type)[0], f.metadata["files"]) for f in fields(Settings) if f.metadata
}


def missing_setting(path: str | Path, key: str) -> ConfigError:
    """``params.yaml: missing setting 'calibrate.method'. Add it ...``, with the key's doc."""
    message = f"{path}: missing setting '{key}'. Add it (see the project's params.yaml for the "
    doc = describe_setting(key.split("."))
    return ConfigError(message + "defaults)." + (f" {key}: {doc}." if doc else ""))


def _partial(model: type, value: Mapping[str, Any], path: str) -> Any:
    """A section that misses required keys, with the keys it gives (each valid)."""
    names, fields_ = fmt.keys_of(model), fmt.fields_of(model)
    types = {k: fields_[names[k]].rebuild_annotation() for k in value if k in names}
    given = {names[k]: TypeAdapter(tp).validate_python(value[k]) for k, tp in types.items()}
    partial = model.model_construct(**given)
    partial._missing_in = path
    return partial


def detect_schema(data: Mapping[str, Any]) -> str:
    """``"fe"`` for a file with an ``fe`` or ``validate`` section (fe/params.yaml), else root."""
    return "fe" if "fe" in data or "validate" in data else "root"


def _sections(data: Mapping, schema: str, complete: bool, path: Any) -> tuple[dict, dict, list]:
    """The typed sections, the partial ones (which only miss keys), and every problem."""
    allowed = [name for name, (_, files) in SECTIONS.items() if schema in files]
    missing = [name for name in allowed if SECTIONS[name][1][schema] and name not in data]
    found, out, partial = [], {}, {}
    for key, value in data.items():
        if key in SECTIONS and key not in allowed:  # fe or validate in a root params file
            where = "belongs to the FE pipeline's fe/params.yaml"
            found.append(((key,), f"{key}: not a section of the root params.yaml; {key} {where}"))
        elif key not in allowed and key != "_path":
            message, close = fmt.unknown_message(
                key, sorted(allowed), missing, what="unknown section"
            )
            found.append(((key,), f"{key}: {message}".replace("{there}", str(close))))
        elif key != "_path":
            model = SECTIONS[key][0]
            try:
                out[key] = model.model_validate(value, context={"complete": complete})
            except ValidationError as exc:
                found += fmt.problems(exc, prefix=(key,), complete=complete)
                kinds = {(e["type"], len(e["loc"])) for e in exc.errors()}
                if kinds == {("missing_setting", 1)}:
                    partial[key] = _partial(model, value, f"{path}:{key}")
    unknown = {fmt.closest(str(k), allowed) for k in data if k not in allowed}
    file = "fe/params.yaml" if schema == "fe" else "params.yaml"
    add = f"missing section; add it (see the project's {file})"
    found += [((n,), f"{n}: {add}") for n in missing if complete and n not in unknown]
    return out, partial, found


def validate_params(
    data: Mapping[str, Any],
    *,
    path: str | Path = "params.yaml",
    schema: str | None = None,
    complete: bool = False,
    text: str | None = None,
    given: Mapping[tuple, str] | None = None,
) -> Settings:
    """The typed :class:`Settings` of a loaded params mapping ``data`` (the file ``path``, its
    ``text`` for line numbers; ``schema`` default :func:`detect_schema`). ``complete`` requires
    every required section and key; otherwise a section missing keys is partial
    (:meth:`Settings.require`). ``given``: path -> the command-line option whose value ``data``
    holds there (messages name it). ConfigError: every unknown, retired, missing
    (``complete``), mistyped or out-of-range setting, each with its line."""
    schema = schema or detect_schema(data)
    if schema not in SCHEMAS:
        raise ConfigError(f"schema must be one of {', '.join(SCHEMAS)}; got {schema!r}.")
    sections, partial, found = _sections(data, schema, complete, path)
    fmt.raise_problems(found, str(path), text, given)
    given = {k: tuple(v) for k, v in data.items() if isinstance(v, Mapping)}
    return Settings(Path(path), schema, given=given, partial=partial, **sections)


def load_settings(path: str | Path = "params.yaml", *, schema: str | None = None) -> Settings:
    """The typed settings of a complete params file (ConfigError: as :func:`validate_params`,
    or the file is missing or not YAML)."""
    from femcal.config import read_yaml_mapping

    data, text = read_yaml_mapping(path)
    return validate_params(data, path=path, schema=schema, complete=True, text=text)


def describe_setting(keys: Iterable[str]) -> str | None:
    """The one-line doc of the setting at ``keys`` (e.g. ``("calibrate", "max_plots")``)."""
    keys = list(keys)
    if not keys or keys[0] not in SECTIONS:
        return None
    model: Any = SECTIONS[keys[0]][0]
    doc = re.sub(r"^``[^`]+``: ", "", model.__doc__.splitlines()[0]).rstrip(".")
    for key in keys[1:]:
        info = model.model_fields.get(key) if fmt.is_model(model) else None
        if info is None:
            return None
        doc, model = info.description, info.annotation
    return doc
