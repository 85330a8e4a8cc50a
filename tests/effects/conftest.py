"""Fixtures of the effect tests."""

from __future__ import annotations

import sys

import pytest

import femcal.effects.base as effects_base
from femcal.effects import effect_registry


@pytest.fixture
def clean_registry():
    """Restore the effect registry (and the loader's bookkeeping) after each test."""
    effect_registry.load()  # the built-in effects register on first import only: keep them
    state = effect_registry.snapshot()
    user_files = dict(effects_base._USER_FILES)
    modules = set(sys.modules)
    yield
    effect_registry.restore(state)
    effects_base._USER_FILES.clear()
    effects_base._USER_FILES.update(user_files)
    for name in set(sys.modules) - modules:
        if name.startswith(("femcal_user_effects_", "femcal_plugin_")):
            del sys.modules[name]
