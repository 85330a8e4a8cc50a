"""Registry of physical effects and their composition with the disc surrogate."""

from femcal.effects.base import (
    Effect,
    EffectParameter,
    available_effects,
    effect_registry,
    get_effect,
    load_effect_modules,
    register_effect,
)

__all__ = [
    "Effect",
    "EffectParameter",
    "available_effects",
    "effect_registry",
    "get_effect",
    "load_effect_modules",
    "register_effect",
]
