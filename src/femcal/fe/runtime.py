"""Where and how FE jobs run: the solver, its settings, the campaign store and the Dask cluster.

The FE stages (``simulate``, ``adapt``, ``validate``) read these from params.yaml once, at the
edge (:func:`fe_runtime`), and run every campaign through one
:class:`FeRuntime`. Nothing here imports pandas, Dask or torch at module level, so that a
stage's settings are read within a second.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Required, TypedDict

if TYPE_CHECKING:
    import pandas as pd

    from femcal.fe.campaign import CampaignResult
    from femcal.fe.options import CampaignOptions
    from femcal.fe.refine import FECurves
    from femcal.space import ParameterSpace


#: Time limit of one attempt of a job, s, for the cohort's and the predictive validation's
#: campaigns (:mod:`femcal.fe.cohort`, :mod:`femcal.fe.predictive`); it replaces
#: ``fe.settings.timeout_s`` there, and their committed stores' job hashes include it. A tight
#: limit would leave out the specimens that solve slowly.
SHARED_MACHINE_TIMEOUT_S = 1200


class FeKeywords(TypedDict, total=False):
    """An :class:`FeRuntime` as keywords (:meth:`FeRuntime.keywords`), for the functions that
    take them one by one (:func:`femcal.stages.validate.run_validate`)."""

    solver: Required[str]
    settings: Required[Mapping[str, Any]]
    store: Required[str | Path]
    scheduler_address: str | None
    n_workers: int
    progress: bool


@dataclass(frozen=True)
class FeRuntime:
    """The FE solver and the machinery its campaigns run on.

    Attributes
    ----------
    solver : str
        Registry name of the solver adapter (``"calculix"``).
    settings : mapping
        The adapter's keyword arguments (e.g. ``{"geometry": "coarse"}``); part of the job hash.
    store : str or Path
        The campaign store, JSON lines (created if missing, resumed if present).
    scheduler_address : str or None
        Dask scheduler to use; None: ``FEMCAL_DASK_ADDRESS``, else a local cluster.
    n_workers : int
        Worker processes of the local cluster.
    progress : bool
        tqdm progress bars.
    """

    solver: str
    settings: Mapping[str, Any]
    store: str | Path
    scheduler_address: str | None = None
    n_workers: int = 2
    progress: bool = False

    def keywords(self) -> FeKeywords:
        """The runtime as the keywords of :func:`femcal.stages.validate.run_validate`."""
        return FeKeywords(
            solver=self.solver,
            settings=self.settings,
            store=self.store,
            scheduler_address=self.scheduler_address,
            n_workers=self.n_workers,
            progress=self.progress,
        )

    def campaign_options(self) -> CampaignOptions:
        """The runtime's cluster and progress bar as the options of
        :func:`femcal.fe.campaign.run_campaign`."""
        from femcal.fe.options import CampaignOptions

        return CampaignOptions(
            scheduler_address=self.scheduler_address,
            n_workers=self.n_workers,
            progress=self.progress,
        )

    def campaign(self, design_df: pd.DataFrame, **options: Any) -> CampaignResult:
        """Run (or resume from the store) every job of a design.

        Parameters
        ----------
        design_df : pandas.DataFrame, shape (n, >= 1 + d)
            ``config_id`` and the parameters.
        **options
            The other keywords of :func:`femcal.fe.campaign.run_campaign` (``names``,
            ``load_cases``, ``moments``, ``forces``) and fields of
            :class:`~femcal.fe.options.CampaignOptions` replacing the runtime's
            (``scratch_dir``, ``retry_failed``, ...).

        Returns
        -------
        CampaignResult
        """
        from femcal.fe.campaign import run_campaign

        return run_campaign(
            self.solver,
            self.settings,
            design_df,
            self.campaign_options(),
            store=self.store,
            **options,
        )

    def curves(self, moments: Sequence[float]) -> FECurves:
        """The FE model as curves: every call a campaign of the four load cases at ``moments``.

        Parameters
        ----------
        moments : sequence of float, shape (m,)
            Moment levels in Nm.

        Returns
        -------
        FECurves
            ``(x (n, 13), ids (n,)) -> RoM (n, 4, m)`` (:func:`femcal.fe.refine.campaign_curves`).
        """
        from femcal.fe.refine import campaign_curves

        return campaign_curves(
            self.solver,
            self.settings,
            store=self.store,
            moments=moments,
            scheduler_address=self.scheduler_address,
            n_workers=self.n_workers,
            progress=self.progress,
        )


def fe_space(bounds: Any) -> ParameterSpace:
    """The sampling box of an FE campaign from ``fe.bounds``.

    Parameters
    ----------
    bounds : str, Path or mapping
        A ParameterBounds.csv file (the study's layout), or a mapping ``name -> [lower,
        upper]`` in physical units (the study's 13 parameters, in the study's order).
    """
    from femcal.errors import ConfigError
    from femcal.space import ParameterSpace

    if isinstance(bounds, (str, Path)):
        return ParameterSpace.from_bounds_csv(Path(bounds))
    if not isinstance(bounds, Mapping) or not bounds:
        raise ConfigError(
            "fe.bounds must be a ParameterBounds.csv path or a mapping name -> [lower, upper]; "
            f"got {bounds!r}."
        )
    try:
        lower = [float(v[0]) for v in bounds.values()]
        upper = [float(v[1]) for v in bounds.values()]
    except (TypeError, ValueError, IndexError, KeyError):
        raise ConfigError(
            "fe.bounds: every entry must be [lower, upper] (two numbers); fix the bounds."
        ) from None
    return ParameterSpace(list(bounds), lower, upper)


def fe_runtime(params: Mapping[str, Any], args: Mapping[str, Any], store_section: str) -> FeRuntime:
    """The FE runtime of a stage, read once from fe/params.yaml and the command line.

    Parameters
    ----------
    params : mapping
        The parsed fe/params.yaml: ``fe.solver``, ``fe.settings``, ``fe.scheduler_address``
        (else ``FEMCAL_DASK_ADDRESS``), ``fe.n_workers`` (default 2).
    args : mapping
        The command line's settings: ``store`` (``--store``) and ``progress``.
    store_section : str
        The section whose ``store`` is the default campaign store (relative to the
        repository's root, :func:`femcal.paths.store_path`).

    Returns
    -------
    FeRuntime
    """
    from femcal.config import settings_of
    from femcal.fe.campaign import scheduler_address_from_env
    from femcal.paths import store_path

    settings = settings_of(params)
    cfg = settings.require("fe", "solver")  # the runtime's keys: the campaign's need not be set
    given = args.get("store")
    return FeRuntime(
        solver=cfg.solver,
        settings=dict(cfg.settings),
        store=Path(given)
        if given
        else store_path(params, settings.require(store_section, "store").store),
        scheduler_address=cfg.scheduler_address or scheduler_address_from_env(),
        n_workers=cfg.n_workers,
        progress=bool(args.get("progress")),
    )
