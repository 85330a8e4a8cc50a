"""Reading params.yaml at the edge: every unknown, missing or wrong key is a clear ConfigError.

:func:`load_params` validates the file against the typed settings of :mod:`femcal.settings`
(root ``params.yaml`` or ``fe/params.yaml``) and returns the file as loaded, with the typed
:class:`~femcal.settings.Settings` as its ``settings`` attribute: the commands read their
sections from it. Nothing heavy is imported here (no torch, Lightning, scikit-learn or
MLflow), so a bad setting is reported before any model or library is loaded.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from femcal.errors import ConfigError

if TYPE_CHECKING:
    from femcal.settings import Settings


class Params(dict):
    """A params file as loaded (a dict, with ``_path``) and its typed :attr:`settings`."""

    settings: Settings


def read_yaml_mapping(path: str | Path) -> tuple[dict[str, Any], str]:
    """The mapping of sections in a YAML file, and the file's text.

    Raises
    ------
    ConfigError
        The file does not exist, is not valid YAML, or does not hold a mapping.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(
            f"Settings file {path} does not exist; run from the project root or pass --params."
        ) from None
    except IsADirectoryError:
        raise ConfigError(
            f"Settings file {path} is a folder; pass the YAML file, e.g. --params "
            f"{path / 'params.yaml'}."
        ) from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path} is not a text file; pass a YAML settings file.") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path} is not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path} must hold a mapping of sections; got {type(data).__name__}.")
    return data, text


def load_params(
    path: str | Path = "params.yaml",
    *,
    schema: str | None = None,
    validate: bool = True,
    overrides: Mapping[tuple[str, ...], tuple[str, Any]] | None = None,
) -> Params:
    """Load and validate a params file; return it as loaded, with its typed settings.

    Parameters
    ----------
    path : str or Path
        ``params.yaml`` (the root pipeline) or ``fe/params.yaml`` (the FE pipeline).
    schema : {"root", "fe"}, optional
        Which file it is; by default ``"fe"`` when the file has an ``fe`` or ``validate``
        section (:func:`femcal.settings.detect_schema`).
    validate : bool
        Check every key the file holds (unknown, retired, mistyped or out-of-range settings
        stop with their path, line and fix). A missing key is reported when a command needs
        its section (:meth:`femcal.settings.Settings.require`);
        :func:`femcal.settings.load_settings` requires them all. Without it, ``settings``
        is None.
    overrides : mapping, optional
        Path of a setting (``("diagnose", "alpha")``) -> (the command-line option that gives
        it, its value), merged into the file's settings before they are validated (a mapping
        value into the file's mapping there); messages name the option.

    Returns
    -------
    Params
        The YAML mapping as loaded (values unchanged), plus ``_path``; its ``settings`` are
        the typed :class:`~femcal.settings.Settings`.

    Raises
    ------
    ConfigError
        The file is missing, not YAML, not a mapping, or holds invalid settings.
    """
    data, text = read_yaml_mapping(path)
    for keys, (_, value) in (overrides or {}).items():
        _merge(data, keys, value)
    params = Params(data, _path=str(path))
    params.settings = None
    if validate:
        from femcal.settings import validate_params

        given = {keys: flag for keys, (flag, _) in (overrides or {}).items()}
        params.settings = validate_params(data, path=path, schema=schema, text=text, given=given)
    return params


def _merge(data: dict[str, Any], keys: tuple[str, ...], value: Any) -> None:
    """Set ``data[k1][k2]... = value``; a mapping is merged into the mapping there."""
    *parents, last = keys
    for key in parents:
        if not isinstance(data.get(key), dict):  # absent or empty: the option gives it
            data[key] = {}
        data = data[key]
    if isinstance(value, dict) and isinstance(data.get(last), dict):
        for key, item in value.items():
            _merge(data[last], (key,), item)
    else:
        data[last] = value


def settings_of(params: Mapping[str, Any]) -> Settings:
    """The typed settings of a loaded params file (validated now when they are not yet)."""
    settings = getattr(params, "settings", None)
    if settings is None:
        from femcal.settings import validate_params

        data = {k: v for k, v in params.items() if k != "_path"}
        settings = validate_params(data, path=params.get("_path", "params.yaml"))
    return settings


def section(params: Mapping[str, Any], *keys: str) -> Any:
    """``params[k1][k2]...`` with an error naming the missing key and the file."""
    node: Any = params
    trail = []
    for key in keys:
        trail.append(key)
        if not isinstance(node, Mapping) or key not in node:
            from femcal.settings.params import missing_setting

            raise missing_setting(params.get("_path", "params.yaml"), ".".join(trail))
        node = node[key]
    return node
