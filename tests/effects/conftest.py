"""Fixtures of the effect tests."""

from __future__ import annotations

import sys

import pytest

import femcal.effects.base as effects_base
from femcal.effects import available_effects


@pytest.fixture
def clean_registry():
    """Restore the effect registry (and the loader's bookkeeping) after each test."""
    available_effects()  # the built-in effects register on first import only: keep them
    saved = (
        dict(effects_base._EFFECTS),
        set(effects_base._ENTRY_POINTS_LOADED),
        effects_base._PLUGINS_DONE,
        dict(effects_base._USER_FILES),
    )
    modules = set(sys.modules)
    yield
    effects_base._EFFECTS.clear()
    effects_base._EFFECTS.update(saved[0])
    effects_base._ENTRY_POINTS_LOADED.clear()
    effects_base._ENTRY_POINTS_LOADED.update(saved[1])
    effects_base._PLUGINS_DONE = saved[2]
    effects_base._USER_FILES.clear()
    effects_base._USER_FILES.update(saved[3])
    for name in set(sys.modules) - modules:
        if name.startswith(("femcal_user_effects_", "femcal_plugin_")):
            del sys.modules[name]
