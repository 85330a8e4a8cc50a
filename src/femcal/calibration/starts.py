"""Where projected gradient descent starts: the training bank, disc-and-effect banks, the grids
and shape designs of effect parameters, and the nearest starts to each specimen."""

from __future__ import annotations

import numpy as np
import torch

from femcal.calibration.base import (
    CalibrationProblem,
)
from femcal.errors import ConfigError

_BANK_BATCH = 8192


def build_bank(problem: CalibrationProblem, start_bank: np.ndarray | None, n_uniform: int, rng):
    """The candidate starts of a calibration and the model's curves at each.

    Parameters
    ----------
    problem : CalibrationProblem
        The problem; its model maps physical parameters to unit coordinates.
    start_bank : ndarray, shape (N, dim) or (N, n_disc), or None
        Given starts in physical units; an effect model takes disc-only starts as well.
    n_uniform : int
        Number of starts drawn uniformly in the unit box.
    rng : numpy.random.Generator
        Draws the uniform starts.

    Returns
    -------
    v : Tensor, shape (N + n_uniform, dim)
        The starts in unit coordinates.
    pred : Tensor, shape (N + n_uniform, 4, m)
        The model's RoM in degrees at each start.

    Raises
    ------
    ConfigError
        ``start_bank`` has neither ``dim`` nor ``n_disc`` columns.
    """
    model = problem.model
    parts = []
    if start_bank is not None and len(start_bank):
        bank = np.asarray(start_bank, dtype=float)
        # An effect model also takes disc-only starts (its effect parameters start mid-box).
        if bank.ndim != 2 or bank.shape[1] not in (model.dim, getattr(model, "n_disc", -1)):
            raise ConfigError(
                f"start_bank must have shape (N, {model.dim}) in physical units; got {bank.shape}."
            )
        parts.append(model.from_physical(bank))
    if n_uniform > 0:
        parts.append(torch.tensor(rng.random((n_uniform, model.dim)), dtype=torch.float32))
    if not parts:
        return torch.zeros((0, model.dim)), torch.zeros((0, 4, len(model.moments)))
    v = torch.cat(parts)
    with torch.no_grad():
        pred = torch.cat(
            [model.curves(v[i : i + _BANK_BATCH]) for i in range(0, v.shape[0], _BANK_BATCH)]
        )
    return v, pred


def effect_bank(
    model, start_bank: np.ndarray, rng: np.random.Generator, n_samples: int = 4096
) -> tuple[torch.Tensor, torch.Tensor]:
    """Random disc-and-effect combinations of an effect model, and their curves.

    A disc fitted alone has bent towards the missing physics, so that an effect started from
    it may never reach the disc it needs. These starts do not depend on that fit: disc
    configurations of the bank, each with every effect either off (its weak start) or on with
    its grid parameters uniform in their box (shape parameters at their classic start); the
    nearest of them to a specimen's curves (:func:`nearest_starts`) join its starts.

    Parameters
    ----------
    model : EffectModel
    start_bank : ndarray, shape (N, n_disc) or (N, dim)
        Disc configurations in physical units (the surrogate's training configurations).
    rng : numpy.random.Generator
    n_samples : int

    Returns
    -------
    v : Tensor, shape (n_samples, dim)
        Unit coordinates.
    pred : Tensor, shape (n_samples, 4, m)
    """
    n_disc = model.n_disc
    bank = np.asarray(start_bank, dtype=float)[:, :n_disc]
    disc = model.base.from_physical(bank)
    v = torch.empty((n_samples, model.dim), dtype=torch.float32)
    v[:, :n_disc] = disc[torch.as_tensor(rng.integers(len(disc), size=n_samples))]
    offset = n_disc
    p_on = 1.0 - 0.5 ** (1.0 / max(len(model.effects), 1))  # half the rows: no effect off
    p_on = max(p_on, 0.5)
    for e in model.effects:
        start = np.array([q.start for q in e.parameters], dtype=float)
        grid = np.array([getattr(q, "grid", True) for q in e.parameters])
        u = np.where(grid, rng.random((n_samples, len(start))), start)
        on = rng.random(n_samples) < p_on
        block = np.where(on[:, None], u, start)
        v[:, offset : offset + len(start)] = torch.tensor(block, dtype=torch.float32)
        offset += len(start)
    with torch.no_grad():
        pred = torch.cat(
            [model.curves(v[i : i + _BANK_BATCH]) for i in range(0, n_samples, _BANK_BATCH)]
        )
    finite = torch.isfinite(pred).reshape(n_samples, -1).all(1)
    return v[finite], pred[finite]


def shape_design(n_parameters: int, n_points: int) -> np.ndarray:
    """A scrambled Sobol design (n_points, n_parameters) in the unit box, fixed seed 0.

    The starts of an effect's shape parameters: a law of the family far from its classic
    member (a soft contact onset, a long toe region) is not reached from the classic member's
    basin by the local optimiser (docs: *Benchmarks > Measurements behind the defaults*).
    """
    if n_points <= 0:
        return np.zeros((0, n_parameters))
    from scipy.stats import qmc

    return qmc.Sobol(n_parameters, scramble=True, seed=0).random(n_points)


def effect_starts(model, levels: tuple[float, ...], shape_starts: int = 0) -> torch.Tensor:
    """Start points of the effect parameters of an effect model, in unit coordinates.

    Parameters
    ----------
    model : EffectModel
    levels : tuple of float
        Unit-box levels of each effect's grid.
    shape_starts : int
        Per effect with shape parameters, also this many points of :func:`shape_design` over
        all of its parameters (the other effects at their weak end).

    Returns
    -------
    Tensor, shape (g, model.dim - model.n_disc)
        Row 0: every effect at its weak end (its parameters' ``start``). Then, per effect, the
        grid ``levels ** n`` over its ``n`` grid parameters (shape parameters stay at their
        start), and the shape design, the other effects at their weak end.
    """
    weak = torch.cat(
        [torch.tensor([q.start for q in e.parameters], dtype=torch.float32) for e in model.effects]
    )
    rows = [weak[None, :]]
    for offset, p, values in _effect_blocks(model, levels, shape_starts):
        block = weak.repeat(len(values), 1)
        block[:, offset : offset + p] = values
        rows.append(block)
    return torch.cat(rows)


def single_effect_starts(
    effect, levels, shape_starts: int = 0, grid_shapes: bool = False
) -> torch.Tensor:
    """Starts (g, p) of one effect's parameters, unit coordinates: the grid ``levels`` over its
    grid parameters (over all of them, shape included, with ``grid_shapes``; the others at their
    classic start), then ``shape_starts`` points of :func:`shape_design` when some parameters
    are not gridded. A law far from the family's classic member (a soft contact onset, say) is
    not reached from the classic member's basin. A split form (:mod:`femcal.effects.split`)
    starts from its tied effect's starts, each value copied into every load case."""
    tied = getattr(effect, "tied", None)
    if tied is not None:
        return effect.expand_tied(single_effect_starts(tied, levels, shape_starts, grid_shapes))
    p = len(effect.parameters)
    start = torch.tensor([q.start for q in effect.parameters], dtype=torch.float32)
    cols = [j for j, q in enumerate(effect.parameters) if getattr(q, "grid", True) or grid_shapes]
    mesh = np.meshgrid(*[np.asarray(levels, dtype=float)] * len(cols), indexing="ij")
    values = start.repeat(mesh[0].size if cols else 1, 1)
    if cols:
        values[:, cols] = torch.tensor(
            np.stack([m.reshape(-1) for m in mesh], 1), dtype=torch.float32
        )
    if shape_starts > 0 and len(cols) < p:
        design = torch.tensor(shape_design(p, shape_starts), dtype=torch.float32)
        values = torch.cat([values, design])
    return values


def _effect_blocks(model, levels, shape_starts: int) -> list[tuple[int, int, torch.Tensor]]:
    """Per effect: its offset among the effect parameters, its size ``p`` and its starts (g, p)
    (:func:`single_effect_starts`)."""
    out = []
    offset = 0
    for e in model.effects:
        out.append((offset, len(e.parameters), single_effect_starts(e, levels, shape_starts)))
        offset += len(e.parameters)
    return out


def combination_starts(model, best: torch.Tensor, levels, shape_starts: int) -> torch.Tensor:
    """Starts (n, 1 + g, d) from each specimen's best solution ``best`` (n, d): itself, then each
    effect's grid and design with the disc and the other effects where ``best`` has them (so a
    second effect can join one the first round found)."""
    n_disc = model.n_disc
    starts = [best[:, None, :]]
    for offset, p, values in _effect_blocks(model, levels, shape_starts):
        block = best[:, None, :].repeat(1, len(values), 1)
        block[:, :, n_disc + offset : n_disc + offset + p] = values[None]
        starts.append(block)
    return torch.cat(starts, dim=1)


def nearest_starts(
    problem: CalibrationProblem, bank_v: torch.Tensor, bank_pred: torch.Tensor, k: int
) -> torch.Tensor:
    """Indices (n, k) of the bank entries whose curves are nearest each specimen's targets."""
    k = min(k, bank_v.shape[0])
    if k == 0:
        return torch.zeros((problem.n_specimens, 0), dtype=torch.long)
    y = problem.target.reshape(problem.n_specimens, -1)
    w = problem.weight.reshape(problem.n_specimens, -1)
    p = bank_pred.reshape(bank_pred.shape[0], -1)
    # sum_k w (p - y)^2 = sum w y^2 - 2 (w y) . p + w . p^2
    dist = (w * y**2).sum(1, keepdim=True) - 2 * (w * y) @ p.T + w @ (p**2).T
    return dist.topk(k, dim=1, largest=False).indices
