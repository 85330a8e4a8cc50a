"""Surrogates of the FE outputs and the baselines, each behind a registry of names."""

from femcal.surrogates.base import (
    Baseline,
    Surrogate,
    available_baselines,
    available_surrogates,
    baseline_registry,
    encode_features,
    get_baseline,
    get_surrogate,
    make_baseline,
    make_surrogate,
    register_baseline,
    register_surrogate,
    surrogate_registry,
)

__all__ = [
    "Baseline",
    "Surrogate",
    "available_baselines",
    "available_surrogates",
    "baseline_registry",
    "encode_features",
    "get_baseline",
    "get_surrogate",
    "make_baseline",
    "make_surrogate",
    "register_baseline",
    "register_surrogate",
    "surrogate_registry",
]
