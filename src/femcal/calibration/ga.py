"""``ga``: the study's genetic algorithm on the frozen surrogate, vectorised over specimens.

The baseline of the reference study ("GA w/ NN", appendix "Calibration baselines", after
Gruber et al. and Nicolini et al.), with the FE model replaced by the surrogate. Individuals
live in the study's min-max unit box ``u`` in [0, 1]^d (linear in the physical parameters).
Per specimen and generation:

1. evaluate the fitness of the population (mean R² over load cases, higher is better;
   optionally the weighted MAE, lower is better);
2. keep the ``n_selected`` best (elitism);
3. add ``n_crossover`` children of random pairs of distinct selected individuals (uniform
   crossover: each gene from either parent with probability 1/2);
4. add ``n_mutation`` copies of random selected individuals with ONE random parameter redrawn
   uniformly in [0, 1];
5. add ``n_immigrants`` uniform random individuals.

Every ``restart_every``-th generation is a restart instead: the best individual plus
``population - 1`` uniform random ones. A specimen stops when its best individual's mean R²
reaches ``target_r2`` or after ``max_generations`` generations.

All specimens' populations are one array (n, population, d); each generation evaluates the
still-running specimens' populations in one call of the surrogate. Every random draw comes
from the given generator, so the same seed gives the same result. The individuals never leave
the box, so the returned parameters are feasible (exceedance 0).
"""

from __future__ import annotations

import dataclasses
import inspect
import logging
from typing import Any

import numpy as np
import torch

from femcal.calibration.base import CalibrationProblem, Solution, register_calibrator
from femcal.calibration.ga_options import GaOptions

logger = logging.getLogger(__name__)


def _evaluate(
    problem: CalibrationProblem, u: np.ndarray, specimens: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Mean R² and MAE of populations ``u`` (k, p, d) of the specimens ``specimens`` (k,).

    Returns two float64 arrays of shape (k, p); a non-finite score counts as the worst.
    """
    k, p, d = u.shape
    model = problem.model
    rows = torch.as_tensor(specimens, dtype=torch.long).repeat_interleave(p)
    with torch.no_grad():
        v = model.from_linear_unit(torch.as_tensor(u.reshape(k * p, d), dtype=torch.float32))
        scores = problem.scores(model.curves(v), rows)
    r2 = scores["r2"].double().numpy().reshape(k, p)
    mae = scores["mae"].double().numpy().reshape(k, p)
    return np.where(np.isfinite(r2), r2, -np.inf), np.where(np.isfinite(mae), mae, np.inf)


def _breed(
    u: np.ndarray,
    key: np.ndarray,
    rng: np.random.Generator,
    *,
    n_selected: int,
    n_crossover: int,
    n_mutation: int,
    n_immigrants: int,
) -> np.ndarray:
    """The next generation (k, p, d) from populations ``u`` (k, p, d) ranked by ``key`` (k, p).

    ``key`` is lower-is-better. Order of the result: selected (best first), crossover
    children, mutants, immigrants.
    """
    k, _, d = u.shape
    order = np.argsort(key, axis=1, kind="stable")[:, :n_selected]
    selected = np.take_along_axis(u, order[:, :, None], axis=1)  # (k, s, d)
    parts = [selected]
    if n_crossover:
        first = rng.integers(0, n_selected, (k, n_crossover))
        second = (first + rng.integers(1, n_selected, (k, n_crossover))) % n_selected
        pa = np.take_along_axis(selected, first[:, :, None], axis=1)
        pb = np.take_along_axis(selected, second[:, :, None], axis=1)
        parts.append(np.where(rng.random((k, n_crossover, d)) < 0.5, pa, pb))
    if n_mutation:
        parent = rng.integers(0, n_selected, (k, n_mutation))
        mutants = np.take_along_axis(selected, parent[:, :, None], axis=1).copy()
        gene = rng.integers(0, d, (k, n_mutation))
        np.put_along_axis(mutants, gene[:, :, None], rng.random((k, n_mutation, 1)), axis=2)
        parts.append(mutants)
    if n_immigrants:
        parts.append(rng.random((k, n_immigrants, d)))
    return np.concatenate(parts, axis=1)


def ga(
    problem: CalibrationProblem,
    options: GaOptions | None = None,
    *,
    rng: np.random.Generator,
    **overrides: Any,
) -> Solution:
    """The study's genetic algorithm for a batch of specimens (see the module docstring).

    Parameters
    ----------
    problem : CalibrationProblem
        Targets of n specimens, shape (n, 4, m), and the surrogate.
    options : GaOptions, optional
        Population, breeding, restarts, stopping and fitness (default: :class:`GaOptions`'s,
        the study's).
    rng : numpy.random.Generator
        Source of every random draw (initial population, pairs, genes, immigrants, restarts).
    **overrides
        Fields of :class:`GaOptions` replacing those of ``options``.

    Returns
    -------
    Solution
        ``x`` (n, d): physical parameters of each specimen's best individual, inside the box;
        ``nit``: generations run (maximum over specimens); ``success`` (n,): best mean R² >=
        ``target_r2``; ``info["generations"]``: generations run per specimen (list of n ints).
        No identifiability ranges.
    """
    o = dataclasses.replace(options or GaOptions(), **overrides)
    best_u, best_r2, generations = _evolve(problem, o, rng)
    return _solution(problem, o, best_u, best_r2, generations)


def _evolve(
    problem: CalibrationProblem, o: GaOptions, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run the generations of every specimen.

    Returns the best individual of each specimen in the unit box (n, d), its mean R² (n,) and
    the generations run per specimen (n,) ints.
    """
    population, target_r2, fitness = o.population, o.target_r2, o.fitness
    n, d = problem.n_specimens, problem.dim
    u = rng.random((n, population, d))
    best_u = np.zeros((n, d))
    best_r2 = np.full(n, -np.inf)
    best_key = np.full(n, np.inf)  # lower is better
    generations = np.zeros(n, dtype=int)
    running = np.ones(n, dtype=bool)
    for gen in range(1, o.max_generations + 1):
        idx = np.flatnonzero(running)
        ua = u[idx]
        r2, mae = _evaluate(problem, ua, idx)
        key = -r2 if fitness == "r2" else mae
        top = key.argmin(1)
        top_key = key[np.arange(idx.size), top]
        better = top_key < best_key[idx]
        improved = idx[better]
        best_key[improved] = top_key[better]
        best_r2[improved] = r2[better, top[better]]
        best_u[improved] = ua[better, top[better]]
        generations[idx] = gen
        running[idx] = best_r2[idx] < target_r2
        logger.debug(
            "ga generation %d: %d running, mean best R² %.4f",
            gen,
            int(running.sum()),
            float(best_r2.mean()),
        )
        if gen == o.max_generations or not running.any():
            break
        # Breed every specimen evaluated this generation (a fixed number of draws per
        # generation and specimen), keep only those still running.
        if gen % o.restart_every == 0:
            fresh = rng.random((idx.size, population - 1, d))
            nxt = np.concatenate([best_u[idx, None, :], fresh], axis=1)
        else:
            nxt = _breed(
                ua,
                key,
                rng,
                n_selected=o.n_selected,
                n_crossover=o.n_crossover,
                n_mutation=o.n_mutation,
                n_immigrants=o.n_immigrants,
            )
        keep = running[idx]
        u[idx[keep]] = nxt[keep]
    return best_u, best_r2, generations


def _solution(
    problem: CalibrationProblem,
    o: GaOptions,
    best_u: np.ndarray,
    best_r2: np.ndarray,
    generations: np.ndarray,
) -> Solution:
    """The :class:`Solution` of :func:`ga` from each specimen's best individual ``best_u``
    (n, d, unit box), its mean R² ``best_r2`` (n,) and its generations run (n,)."""
    n = problem.n_specimens
    model = problem.model
    x = model.space.clip(model.linear_unit_to_physical(np.clip(best_u, 0.0, 1.0)))
    success = best_r2 >= o.target_r2
    nit = int(generations.max()) if n else 0
    message = (
        f"ga: population {o.population} ({o.n_selected} selected, {o.n_crossover} crossover, "
        f"{o.n_mutation} mutation, {o.n_immigrants} immigrants), restart every "
        f"{o.restart_every}, {nit} generations at most, {int(success.sum())}/{n} reached mean "
        f"R² >= {o.target_r2:g}"
    )
    logger.info(message)
    return Solution(
        x=x,
        nit=nit,
        success=success,
        message=message,
        info={
            "generations": generations.tolist(),
            "generations_mean": float(generations.mean()) if n else 0.0,
            "best_r2": best_r2.tolist(),
            "fitness": o.fitness,
            "population": o.population,
            "n_selected": o.n_selected,
            "n_crossover": o.n_crossover,
            "n_mutation": o.n_mutation,
            "n_immigrants": o.n_immigrants,
            "restart_every": o.restart_every,
            "max_generations": o.max_generations,
            "target_r2": o.target_r2,
        },
    )


@register_calibrator("ga")
def calibrate_ga(
    problem: CalibrationProblem, *, rng: np.random.Generator, **options: Any
) -> Solution:
    """The registered ``ga`` calibrator: :func:`ga` with the keywords of :class:`GaOptions`."""
    return ga(problem, GaOptions(**options), rng=rng)


calibrate_ga.__signature__ = inspect.Signature(
    [
        *list(inspect.signature(ga).parameters.values())[:1],
        list(inspect.signature(ga).parameters.values())[2],
        *(
            inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, default=f.default)
            for f in dataclasses.fields(GaOptions)
        ),
    ],
    return_annotation=Solution,
)
