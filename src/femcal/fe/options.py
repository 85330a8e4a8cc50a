"""The options of the FE workflows, each default declared here once.

:class:`GeometryOptions` (the disc of :class:`femcal.fe.geometry.DiscGeometry`),
:class:`CampaignOptions` (how :func:`femcal.fe.campaign.run_campaign` runs its jobs),
:class:`AdaptOptions` (:func:`femcal.fe.adaptive.adapt_surrogate`) and
:class:`ValidateOptions` (:func:`femcal.fe.validate.validate_calibration`). The options that
fe/params.yaml sets are declared here once (:func:`femcal.settings.values.option`: type with
bounds, default, doc); its sections are built from them, so this module imports nothing
heavy.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from femcal.errors import ConfigError
from femcal.settings.values import DASK_ADDRESS, PATH, Float, Int, check_options, option

if TYPE_CHECKING:
    import numpy as np

    from femcal.fe.validate import LiteratureRange
    from femcal.settings.fe import PublishedIdp


@dataclass(frozen=True)
class GeometryOptions:
    """The disc's dimensions, regions and mesh density (:class:`femcal.fe.geometry.DiscGeometry`
    adds its mesh), as ``fe.settings.geometry`` sets them.

    Raises
    ------
    ConfigError
        A field out of its bounds: ``DiscGeometry: n_regions must be an integer >= 3; got 2.``
    """

    width_mm: Float(gt=0) = option(50.0, "lateral axis of the ellipse, mm")
    depth_mm: Float(gt=0) = option(35.0, "anterior-posterior axis of the ellipse, mm")
    height_mm: Float(gt=0) = option(11.0, "disc height, mm")
    nucleus_fraction: Float(gt=0, lt=1) = option(0.44, "nucleus volume fraction")
    n_rings: Int(1) = option(
        5, "annulus rings from the outer to the inner boundary (material layers)"
    )
    n_regions: Int(3) = option(5, "circumferential annulus regions per side, anterior to posterior")
    elements_per_region: Int(1) = option(1, "elements along the circumference per region")
    elements_per_ring: Int(1) = option(1, "elements across each annulus ring")
    elements_core: Int(1) = option(1, "elements between the nucleus block and its boundary")
    elements_height: Int(1) = option(2, "elements through the disc height")
    core_size: Float(gt=0, lt=1) = option(
        0.55, "corner radius of the nucleus block relative to the nucleus radius"
    )
    reference_height_mm: Float() = option(
        10.0, "load reference point above the disc centre, mm (study: 10 mm)"
    )

    def __post_init__(self) -> None:
        check_options(self, type(self).__name__)


@dataclass(frozen=True)
class CampaignOptions:
    """Where and how :func:`~femcal.fe.campaign.run_campaign` runs the jobs of a design.

    Attributes
    ----------
    scheduler_address : str or None
        Dask scheduler to use, ``tcp://host:port``; None: ``FEMCAL_DASK_ADDRESS``, else a local
        cluster.
    n_workers : int
        Worker processes of the local cluster (one single-threaded FE solver each).
    scratch_dir : str or Path or None
        Parent folder of the per-job scratch folders; None: the worker's temporary folder.
    keep_failed : bool
        Keep failed jobs' scratch folders (their path is in the record).
    retry_failed : bool or callable
        Run stored failed jobs again: all of them (True), or those whose stored record the
        predicate accepts (e.g. :func:`~femcal.fe.campaign.timed_out`). False: a failure is a
        result and is kept.
    progress : bool
        Show a tqdm progress bar.
    """

    scheduler_address: DASK_ADDRESS | None = option(
        None, "Dask scheduler, tcp://host:port (null: a local cluster, or FEMCAL_DASK_ADDRESS)"
    )
    n_workers: Int(1) = option(2, "workers of the local cluster")
    scratch_dir: PATH | None = option(None, "per-job scratch (null: temp)")
    keep_failed: bool = True
    retry_failed: bool | Callable[[Mapping[str, Any]], bool] = False
    progress: bool = True

    def __post_init__(self) -> None:
        check_options(self, "run_campaign")


@dataclass(frozen=True)
class AdaptOptions:
    """How :func:`~femcal.fe.adaptive.adapt_surrogate` samples, fine-tunes and numbers its runs.

    Attributes
    ----------
    rounds : int
        Rounds of FE runs and fine-tuning, >= 1.
    n_explore : int
        Configurations run per round where the ensemble's members disagree most, >= 0.
    n_candidates : int
        Latin-hypercube candidates ranked by the ensemble spread, of which the ``n_explore``
        most disputed run; >= ``n_explore`` and >= 1.
    finetune : mapping or None
        ``set_params`` of the fine-tuning, replacing those of the default fine-tuning
        (``max_epochs=100``, ``patience=100``, ``val_fraction=0``, ``learning_rate`` a third
        of the surrogate's, in its units); None: the default fine-tuning.
    calibrate_options : mapping or None
        Options of the rounds' ``pgd`` calibrations; None: the calibrator's defaults.
    seed : int or numpy.random.Generator
        Seeds the candidates and the calibrations; the same seed gives the same runs.
    first_id : int
        The first configuration number of the new runs (keep them apart from a store's).

    Raises
    ------
    ConfigError
        When ``rounds < 1``, ``n_explore < 0`` or ``n_candidates < max(1, n_explore)``.
    """

    rounds: Int(1) = option(3, "rounds of FE runs and fine-tuning")
    n_explore: Int(0) = option(16, "configurations explored per round (ensemble spread)")
    n_candidates: Int(1) = option(2048, "Latin-hypercube candidates ranked by spread")
    finetune: Mapping[str, Any] | None = None
    calibrate_options: Mapping[str, Any] | None = None
    seed: int | np.random.Generator = 0
    first_id: int = 0

    def __post_init__(self) -> None:
        rounds, n_explore, n_candidates = self.rounds, self.n_explore, self.n_candidates
        if int(rounds) < 1 or int(n_explore) < 0 or int(n_candidates) < max(1, int(n_explore)):
            raise ConfigError(
                f"adapt_surrogate needs rounds >= 1, n_explore >= 0 and n_candidates >= n_explore; "
                f"got {rounds}, {n_explore}, {n_candidates}."
            )
        check_options(self, "adapt_surrogate")


@dataclass(frozen=True)
class ValidateOptions:
    """What :func:`~femcal.fe.validate.validate_calibration` checks besides the moments, and
    how far it refines the calibration with FE in the loop first.

    Attributes
    ----------
    forces : sequence of float
        Axial compressive forces in N for the IDP check, e.g. (300, 1000, 2000); empty: no
        compression runs.
    literature : sequence of LiteratureRange
        Published in vitro IDP ranges (MPa) at a force to compare with; forces without a range
        are reported without a verdict.
    published : sequence of PublishedIdp
        Published pressures (MPa) without a known force (in vivo postures): the force at which
        each disc reaches them goes to ``idp_published.csv`` (:mod:`femcal.fe.idp`).
    max_fe_runs : int
        FE runs per specimen at most in the FE-in-the-loop refinement, the first included
        (1: no refinement, validate the calibration as is).
    tol_deg : float
        FE-evaluated MAE in degrees at which refinement stops for a specimen.
    """

    forces: Sequence[float] = ()
    literature: Sequence[LiteratureRange] = ()
    published: Sequence[PublishedIdp] = ()
    max_fe_runs: Int(1) = option(
        1, "FE runs per specimen at most, the first included (1: validate only)"
    )
    tol_deg: Float(gt=0) = option(0.05, "FE-evaluated MAE at which a specimen is confirmed, deg")

    def __post_init__(self) -> None:
        check_options(self, "validate_calibration")
