"""Reading params.yaml at the edge: every missing or wrong key is a clear ConfigError."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from femcal.errors import ConfigError


def load_params(path: str | Path = "params.yaml") -> dict[str, Any]:
    """Load a params file as a dict."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(
            f"Settings file {path} does not exist; run from the project root or pass --params."
        ) from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path} is not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path} must hold a mapping of sections; got {type(data).__name__}.")
    data["_path"] = str(path)
    return data


def section(params: Mapping[str, Any], *keys: str) -> Any:
    """``params[k1][k2]...`` with an error naming the missing key and the file."""
    node: Any = params
    trail = []
    for key in keys:
        trail.append(key)
        if not isinstance(node, Mapping) or key not in node:
            raise ConfigError(
                f"{params.get('_path', 'params.yaml')}: missing setting '{'.'.join(trail)}'. "
                "Add it (see the project's params.yaml for the defaults)."
            )
        node = node[key]
    return node
