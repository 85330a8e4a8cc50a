"""Surrogates of the FE outputs, behind one registry of names."""

from femcal.surrogates.base import (
    Surrogate,
    available_surrogates,
    encode_features,
    get_surrogate,
    make_surrogate,
    register_surrogate,
    surrogate_registry,
)

__all__ = [
    "Surrogate",
    "available_surrogates",
    "encode_features",
    "get_surrogate",
    "make_surrogate",
    "register_surrogate",
    "surrogate_registry",
]
