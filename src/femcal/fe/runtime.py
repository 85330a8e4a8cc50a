"""Where and how FE jobs run: the solver, its settings, the campaign store and the Dask cluster.

The FE stages (``simulate``, ``adapt``, ``validate``) read these from params.yaml once, at the
edge (:func:`femcal.stages.simulate.fe_runtime`), and run every campaign through one
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


#: Wall-clock limit of one attempt of a job, s, for the campaigns that run niced on a shared
#: machine (:mod:`femcal.fe.cohort`, :mod:`femcal.fe.predictive`); it replaces
#: ``fe.settings.timeout_s`` there. A tight limit would turn the machine's load into
#: failures, and leaving those out would favour specimens that solve fast.
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
