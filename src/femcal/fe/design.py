"""The sampling design of an FE campaign: a seeded Latin hypercube per split, scaled to the box."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
from scipy.stats import qmc

from femcal.errors import ConfigError
from femcal.space import ParameterSpace

#: How a split of a study-like design is sampled (the study: LHS for Large/Small, random Test).
SPLIT_SAMPLING: dict[str, str] = {"large": "lhs", "small": "lhs", "test": "uniform"}


# --------------------------------------------------------------------------- designs
def latin_hypercube(space: ParameterSpace, n: int, rng: np.random.Generator) -> np.ndarray:
    """A Latin hypercube of ``n`` points over the parameter box (:class:`scipy.stats.qmc`).

    :class:`scipy.stats.qmc.LatinHypercube` draws the points in the unit cube, one per
    stratum ``[j/n, (j+1)/n)`` of every parameter, each placed at random inside its cell
    (``scramble=True``); :func:`scipy.stats.qmc.scale` maps them to the bounds.

    Parameters
    ----------
    space : ParameterSpace
        Names and bounds (physical units).
    n : int
        Number of points (>= 1).
    rng : numpy.random.Generator
        Drives the sampler (and is advanced by it): the same generator state gives the same
        points.

    Returns
    -------
    ndarray, shape (n, d)
        Physical units, within the bounds (``qmc.scale`` maps [0, 1) to [lower, upper)).
    """
    # ``seed=`` (not ``rng=``, scipy >= 1.15 only): the keyword of every scipy >= 1.11;
    # a Generator is used as is by both.
    sampler = qmc.LatinHypercube(d=space.dim, scramble=True, seed=rng)
    return qmc.scale(sampler.random(int(n)), space.lower, space.upper)


def design(
    space: ParameterSpace, n: int, rng: np.random.Generator, *, method: str = "lhs"
) -> pd.DataFrame:
    """A design of ``n`` configurations over the parameter box.

    Parameters
    ----------
    space : ParameterSpace
        Names and bounds (physical units).
    n : int
        Number of configurations (>= 1).
    rng : numpy.random.Generator
        The only source of randomness: the same generator state gives the same design.
    method : {"lhs", "uniform"}, optional
        Latin hypercube (default, :func:`latin_hypercube`) or independent uniform draws.

    Returns
    -------
    pandas.DataFrame, shape (n, 1 + d)
        ``config_id`` (0 .. n-1) and the d parameters in physical units, in ``space.names``
        order.
    """
    if int(n) < 1:
        raise ConfigError(f"A design needs at least one configuration; got n={n}.")
    if method == "lhs":
        x = latin_hypercube(space, int(n), rng)
    elif method == "uniform":
        x = space.sample_uniform(int(n), rng)
    else:
        raise ConfigError(f"Unknown design method {method!r}; use 'lhs' or 'uniform'.")
    x = space.clip(x)  # guard against rounding at the upper bound
    df = pd.DataFrame(x, columns=list(space.names))
    df.insert(0, "config_id", np.arange(int(n), dtype=np.int64))
    return df


def batch_space(
    space: ParameterSpace, batch: int | Mapping, index: int
) -> tuple[int, ParameterSpace]:
    """The size and the box of one further batch of the large split.

    Parameters
    ----------
    space : ParameterSpace
        The campaign's box.
    batch : int or mapping
        A number of configurations (a Latin hypercube over the whole box), or ``{"n": int,
        "bounds": {name: [lower, upper]}}``: a Latin hypercube over the box narrowed to the
        given ranges (each inside the campaign's box), e.g. the soft corner where the
        surrogate errs most.
    index : int
        The batch's position in ``fe.batches`` (0-based), for messages.

    Returns
    -------
    n : int
    box : ParameterSpace
        ``space`` with the given ranges replaced.
    """
    where = f"fe.batches[{index}]"
    if not isinstance(batch, Mapping):
        return int(batch), space
    lower, upper = space.lower.copy(), space.upper.copy()
    for name, pair in dict(batch.get("bounds") or {}).items():
        if name not in space.names:
            raise ConfigError(
                f"{where}.bounds names {name!r}, not a parameter of the box; use one of "
                f"{list(space.names)}."
            )
        k = space.names.index(name)
        lo, hi = (float(v) for v in pair)
        if not space.lower[k] <= lo < hi <= space.upper[k]:
            raise ConfigError(
                f"{where}.bounds.{name} is [{lo:g}, {hi:g}]; a batch narrows the box, so give "
                f"lower < upper inside fe.bounds' [{space.lower[k]:g}, {space.upper[k]:g}] "
                "(widen fe.bounds first to sample beyond it)."
            )
        lower[k], upper[k] = lo, hi
    box = ParameterSpace(space.names, lower, upper, units=space.units, scales=space.scales)
    return int(batch.get("n", 0)), box


def split_design(
    space: ParameterSpace,
    counts: Mapping[str, int],
    seed: int,
    batches: Sequence[int | Mapping] = (),
) -> pd.DataFrame:
    """One design holding the splits of a study-like dataset (Large, Small, Test).

    Every split is sampled with its own generator ``default_rng([seed, k])`` (k = index of
    the split name in ``("large", "small", "test")``), so changing one split's size leaves
    the others unchanged. Large and Small are Latin hypercubes, Test is uniform random, as in
    the study (:data:`SPLIT_SAMPLING`).

    ``batches`` grows the large split without touching a stored job: batch ``b`` (1, 2, ...)
    is a Latin hypercube of its own drawn with ``default_rng([seed, 0, b])``, numbered after
    every split and every earlier batch, so each configuration keeps its ``config_id`` (part
    of the job hash) when a batch is added. A batch given as ``{"n": ..., "bounds": ...}``
    samples a narrowed box (:func:`batch_space`).

    Parameters
    ----------
    space : ParameterSpace
    counts : mapping of str to int
        Configurations per split, e.g. ``{"large": 96, "small": 24, "test": 16}``.
    seed : int
    batches : sequence of int or mapping, optional
        The further batches of the large split: sizes (each >= 1), or mappings ``{"n": int,
        "bounds": {name: [lower, upper]}}`` over a narrowed box (:func:`batch_space`).

    Returns
    -------
    pandas.DataFrame, shape (sum(counts), 2 + d)
        ``config_id`` (0 .. N-1 over all splits, in split order), ``split`` and the
        parameters.
    """
    order = list(SPLIT_SAMPLING)
    unknown = sorted(set(counts) - set(order))
    if unknown:
        raise ConfigError(
            f"Unknown split(s) {unknown} in fe.splits; use {order} (the study's folders)."
        )
    frames = []
    for k, name in enumerate(order):
        n = int(counts.get(name, 0) or 0)
        if n < 0:
            raise ConfigError(f"fe.splits.{name} must be a number of configurations >= 0.")
        if n == 0:
            continue
        part = design(space, n, np.random.default_rng([int(seed), k]), method=SPLIT_SAMPLING[name])
        part.insert(1, "split", name)
        frames.append(part)
    if not frames:
        raise ConfigError("fe.splits asks for no configurations; give at least one split > 0.")
    for b, batch in enumerate(batches, start=1):
        n, box = batch_space(space, batch, b - 1)
        if n < 1:
            raise ConfigError(
                f"fe.batches[{b - 1}] has {n} configurations; each batch is a number of "
                "configurations >= 1 (remove the entry instead)."
            )
        part = design(box, n, np.random.default_rng([int(seed), 0, b]), method="lhs")
        part.insert(1, "split", "large")
        frames.append(part)
    df = pd.concat(frames, ignore_index=True)
    df["config_id"] = np.arange(len(df), dtype=np.int64)
    return df
