"""The Optuna search of a training, as one typed object the trainers and the stages share.

The surrogate (:func:`femcal.train.train_surrogate`) and the inverse model
(:func:`femcal.inverse.train.train_inverse`) take the same search keywords
(:class:`StudyKeywords`); the training stages read them from params.yaml once
(:func:`femcal.stages.common.study_search`). Nothing here imports Optuna, Lightning or
MLflow at module level, so that a stage's settings are read within a second.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any, TypedDict

if TYPE_CHECKING:
    from femcal.training.study import TrialRun


class StudyKeywords(TypedDict, total=False):
    """The keywords of a :class:`StudySearch`, as the trainers take them."""

    search_space: Mapping[str, Mapping[str, Any]] | None
    fixed: Mapping[str, Any] | None
    n_trials: int
    storage: str | None
    study_name: str
    seed: int
    heartbeat_seconds: int
    progress: bool


@dataclass(frozen=True)
class StudySearch:
    """An Optuna search of a model's settings, resumable in an RDB storage.

    Attributes
    ----------
    study_name : str
        Base name of the study; :meth:`named` appends a hash of the problem.
    search_space : mapping
        Optuna search space (:func:`femcal.training.study.suggest`); None is empty.
    fixed : mapping
        Fixed settings, overridden by the search; enqueued as trial 0 where inside the space.
        None is empty.
    n_trials : int
        Complete trials the study should hold; a resumed study only runs the missing ones.
        0 runs no study: the final model is fitted on ``fixed`` alone.
    storage : str or None
        Optuna RDB storage URL (``sqlite:///...`` or any SQLAlchemy URL); needed when
        ``n_trials > 0``.
    seed : int
        Seeds the sampler (and, in the trainers, the data split and every fit).
    heartbeat_seconds : int
        Trials send a heartbeat this often; a trial silent for three periods (its worker was
        killed) is marked failed and retried.
    progress : bool
        Progress bars of Optuna (and, in the trainers, of Lightning).
    """

    study_name: str
    search_space: Mapping[str, Mapping[str, Any]] | None = field(default_factory=dict)
    fixed: Mapping[str, Any] | None = field(default_factory=dict)
    n_trials: int = 0
    storage: str | None = None
    seed: int = 0
    heartbeat_seconds: int = 30
    progress: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "search_space", dict(self.search_space or {}))
        object.__setattr__(self, "fixed", dict(self.fixed or {}))

    def keywords(self) -> StudyKeywords:
        """The search as the trainers' keywords."""
        return StudyKeywords(**{f.name: getattr(self, f.name) for f in fields(self)})

    def named(self, data_id: str) -> str:
        """The full study name: :attr:`study_name` with a hash of the search space, the fixed
        settings and ``data_id`` (:func:`femcal.training.study.study_name_for`)."""
        from femcal.training.study import study_name_for

        return study_name_for(
            self.study_name, search_space=self.search_space, fixed=self.fixed, data_id=data_id
        )

    def run(
        self, train_trial: Callable[[TrialRun], float], *, name: str, metric: str, monitor: str
    ) -> tuple[dict[str, Any], int]:
        """Run (or resume) the study in the active MLflow run (:func:`search_settings`).

        Parameters
        ----------
        train_trial : callable
            ``(TrialRun) -> float``, see :func:`femcal.training.study.run_study`.
        name : str
            The full study name (:meth:`named`).
        metric : str
            Name of the objective in the logged metric ``best_trial_<metric>``.
        monitor : str
            The logged validation metric the pruner watches.

        Returns
        -------
        tuple of (dict, int)
            The best settings and the complete trials, as
            :func:`femcal.training.study.search_settings` returns them.
        """
        from femcal.training.study import search_settings

        return search_settings(
            train_trial,
            fixed=self.fixed,
            n_trials=self.n_trials,
            metric=metric,
            storage=self.storage,
            study_name=name,
            search_space=self.search_space,
            seed=self.seed,
            monitor=monitor,
            heartbeat_seconds=self.heartbeat_seconds,
            progress=self.progress,
        )
