"""The DVC stages, one module each: read settings, call the library, write outputs.

Each module holds a frozen settings dataclass built from params.yaml and the command line
(``<Name>Settings.from_params(params, args)``, which also checks outputs and inputs before
anything heavy is imported), ``run(settings) -> dict`` (the stage's figures) and
``describe(figures) -> list[str]`` (the lines ``femcal`` prints). ``femcal.cli`` parses the
command line and dispatches here; tests and notebooks call ``run`` or the stage's ``run_*``
library function directly.

=================  ==========================  ==================================
command            module                      stage (dvc.yaml / fe/dvc.yaml)
=================  ==========================  ==================================
``fetch``          :mod:`.fetch`               fetch
``prepare``        :mod:`.prepare`             prepare
``train``          :mod:`.train`               train@large, train@small, ...
``baselines``      :mod:`.baselines`           baselines@large, baselines@small
``interpolate``    :mod:`.interpolate`         interpolate
``evaluate``       :mod:`.evaluate`            evaluate
``train-inverse``  :mod:`.train_inverse`       train-inverse
``calibrate``      :mod:`.calibrate`           calibrate@test, calibrate@planted
``plant``          :mod:`.plant`               plant
``diagnose``       :mod:`.diagnose`            diagnose
``simulate``       :mod:`.simulate`            simulate (fe/dvc.yaml)
``adapt``          :mod:`.adapt`               adapt (fe/dvc.yaml)
``validate``       :mod:`.validate`            validate (fe/dvc.yaml)
=================  ==========================  ==================================
"""

from __future__ import annotations

import importlib
from types import ModuleType

#: Sub-command -> module of this package.
COMMANDS: dict[str, str] = {
    "fetch": "fetch",
    "prepare": "prepare",
    "train": "train",
    "baselines": "baselines",
    "interpolate": "interpolate",
    "evaluate": "evaluate",
    "train-inverse": "train_inverse",
    "calibrate": "calibrate",
    "plant": "plant",
    "diagnose": "diagnose",
    "simulate": "simulate",
    "adapt": "adapt",
    "validate": "validate",
}


def stage_module(command: str) -> ModuleType:
    """The module of a sub-command (imported on first use: the CLI stays light)."""
    return importlib.import_module(f"{__name__}.{COMMANDS[command]}")


def settings_class(module: ModuleType) -> type:
    """The settings dataclass of a stage module (the one ``*Settings`` class it defines)."""
    (cls,) = [
        v
        for k, v in vars(module).items()
        if k.endswith("Settings") and isinstance(v, type) and v.__module__ == module.__name__
    ]
    return cls
