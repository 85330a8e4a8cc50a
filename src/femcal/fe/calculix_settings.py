"""The CalculiX adapter's keyword arguments (:class:`CalculixSettings`, ``fe.settings``): the
disc geometry and the posterior elements, whose parameters, units, ranges and defaults are
declared here once. Axes as the disc model's (x lateral, y anterior, z cranial; lower endplate
at z = 0, disc centre at x = y = 0); sources and calibration: docs/fe-posterior-elements.md.
This module imports nothing heavy: :mod:`femcal.settings.fe` reads it with
:func:`~femcal.settings.values.light_class`.
"""

from typing import Any, ClassVar, Literal

from pydantic import ConfigDict, TypeAdapter, ValidationError, model_validator
from pydantic.dataclasses import dataclass

from femcal.errors import ConfigError
from femcal.settings._format import fail, got, one_of, problems, reword
from femcal.settings.keywords import MESH_PRESETS
from femcal.settings.values import (
    NAME,
    Bool,
    Float,
    Int,
    Keywords,
    OptionSection,
    keyword,
    light_class,
    plain,
    setting,
    with_options,
)


def _element(cls: type) -> type:
    """A posterior element's settings: a frozen pydantic dataclass, every key known."""
    cls._reword = model_validator(mode="wrap")(classmethod(reword))
    return dataclass(frozen=True, config=ConfigDict(extra="forbid"))(cls)


@_element
class FacetSettings:
    """``fe.settings.posterior.facets``: two facet joints, each a unilateral gap element: a
    CalculiX ``GAPUNI`` between a node tied to the upper endplate and a fixed one at
    ``(+-lateral_mm, -posterior_mm, height_mm)``, closed once the upper node has moved ``gap_mm``
    along the contact normal (``axial_angle_deg`` from lateral, tilted ``inclination_deg`` down).
    """

    _complete: ClassVar[bool] = True

    gap_mm: Float(0, 3) = setting("facet joint clearance, mm", 0.5)
    stiffness_n_per_mm: Float(1, 1e5) = setting("contact stiffness of a closed facet, N/mm", 50.0)
    lateral_mm: Float(5, 40) = setting("distance from the mid-sagittal plane, mm", 16.0)
    posterior_mm: Float(18, 60) = setting("distance behind the disc centre, mm", 30.0)
    height_mm: Float(-20, 30) = setting("centre height above the lower endplate, mm", 5.5)
    axial_angle_deg: Float(0, 90) = setting("joint plane to sagittal plane (top view), deg", 45.0)
    inclination_deg: Float(0, 80) = setting("downward tilt of the contact normal, deg", 30.0)


@_element
class LigamentSettings:
    """One ligament: a tension-only nonlinear spring (``SPRINGA``), one per side if lateral,
    vertical at ``(+-lateral_mm, -posterior_mm, height_mm)``, rest length ``length_mm``: no
    force below the elongation ``slack_strain * length_mm``, a quadratic toe over the next
    ``toe_strain * length_mm`` up to the slope ``stiffness_n_per_mm``, then that slope.
    """

    _complete: ClassVar[bool] = True

    stiffness_n_per_mm: Float(0.1, 1000) = setting("linear-region stiffness (each side), N/mm")
    toe_strain: Float(0, 1) = setting("strain span of the toe region")
    slack_strain: Float(-0.3, 0.5) = setting("strain at which force starts (< 0: pre-strained)")
    lateral_mm: Float(0, 60) = setting("distance from the mid-sagittal plane (0: midline), mm")
    posterior_mm: Float(0, 100) = setting("distance behind the disc centre, mm")
    height_mm: Float(-30, 40) = setting("centre above the lower endplate, mm")
    length_mm: Float(0.5, 60) = setting("rest length (upper to lower attachment), mm")


#: Default properties and attachment of each ligament (the fields of :class:`LigamentSettings`):
#: stiffness from Pintar et al. 1992 and Guo et al. 2021, rest lengths from Naserkhaki et al.
#: 2018, slack strains calibrated to the segment-to-disc RoM ratios (docs/fe-posterior-elements.md).
LIGAMENT_DEFAULTS: dict[str, dict[str, float]] = {
    name: dict(zip(LigamentSettings.__pydantic_fields__, row, strict=True))
    for name, *row in (
        # name, stiffness_n_per_mm, toe_strain, slack_strain, lateral, posterior, height, length
        ("supraspinous", 23.7, 0.20, 0.45, 0.0, 60.0, 5.5, 27.49),
        ("interspinous", 11.6, 0.139, 0.45, 0.0, 45.0, 5.5, 8.85),
        ("flavum", 27.2, 0.059, 0.45, 0.0, 35.0, 5.5, 15.89),
        ("capsular", 33.9, 0.25, 0.45, 18.0, 30.0, 5.5, 10.0),
        ("intertransverse", 10.7, 0.182, 0.0, 35.0, 22.0, 5.5, 18.69),
    )
}
#: The ligaments the model knows.
LIGAMENTS: tuple[str, ...] = tuple(LIGAMENT_DEFAULTS)
_LIGAMENTS = f"tension-only ligaments ({', '.join(LIGAMENTS)}): a list, or name -> overrides"


@with_options(**{n: (LigamentSettings, setting(f"the {n} ligament", None)) for n in LIGAMENTS})
class Ligaments(Keywords):
    """``fe.settings.posterior.ligaments``: ligament -> its settings (the defaults overridden)."""

    _unknown: ClassVar[str] = "unknown ligament"
    _describe: ClassVar[str] = "a list of ligament names or a mapping name -> settings"

    @model_validator(mode="before")
    @classmethod
    def _with_defaults(cls, value: Any) -> Any:
        value = {name: {} for name in value} if isinstance(value, list | tuple) else value
        if not isinstance(value, dict):
            return value
        for name, overrides in value.items():
            if overrides is not None and not isinstance(overrides, dict):
                raise fail(f"expected a mapping of ligament settings, got {got(overrides)}", name)
        defaults = LIGAMENT_DEFAULTS
        return {k: {**defaults[k], **(v or {})} if k in defaults else v for k, v in value.items()}


@_element
class PosteriorSettings:
    """``fe.settings.posterior``: the posterior elements joined to the disc (all optional;
    null ``facets`` and no ``ligaments``: the disc alone)."""

    _complete: ClassVar[bool] = True
    _describe: ClassVar[str] = "a mapping (facets, ligaments) or null"

    facets: FacetSettings | None = setting("facet joints (GAPUNI contact; null: none)", None)
    ligaments: plain(Ligaments, typed=True) = setting(_LIGAMENTS, {})

    @model_validator(mode="before")
    @classmethod
    def _a_mapping(cls, value: Any) -> Any:
        return {} if value is None else value  # ArgsKwargs: PosteriorSettings(facets=...)

    @property
    def active(self) -> bool:
        """Whether any posterior element is present."""
        return self.facets is not None or bool(self.ligaments)


@with_options
class GeometryKeywords(OptionSection, Keywords):
    """The disc geometry (femcal.fe.geometry.DiscGeometry)."""

    _owner: ClassVar[str] = "DiscGeometry"
    _describe: ClassVar[str] = "a mesh preset (coarse, default, fine) or DiscGeometry fields"
    _options: ClassVar[type] = light_class("fe.options", "GeometryOptions")

    @model_validator(mode="before")
    @classmethod
    def _preset(cls, value: Any) -> Any:
        if isinstance(value, str) and value in MESH_PRESETS:
            return {"preset": value}
        if isinstance(value, str):
            raise fail(one_of(value, MESH_PRESETS))
        return value

    preset: Literal[MESH_PRESETS] = keyword("mesh density the other fields start from")


class CalculixSettings(Keywords):
    """The CalculiX adapter's keyword arguments (``fe.settings``; part of every job's hash)."""

    _owner: ClassVar[str] = "CalculixDisc"

    geometry: plain(GeometryKeywords) = keyword("a mesh preset (coarse, default, fine) or fields")
    kappa: Literal["scale", "ignore"] = keyword("how the fibre dispersion Kappa enters")
    executable: NAME = keyword("the CalculiX executable")
    initial_increment: Float(gt=0, le=1) = keyword("first load increment")
    max_attempts: Int(1) = keyword("attempts per job (retries of a fibre-routine abort)")
    timeout_s: Float(gt=0) | None = keyword("CPU seconds per attempt (null = none)")
    max_increments: Int(1) = keyword("load increments at most")
    retry_factor: Float(gt=0, le=1) = keyword("increment factor of a retry")
    nucleus_d1: Float(gt=0) = keyword("compressibility of the nucleus")
    annulus_d1: Float(gt=0) = keyword("compressibility of the annulus")
    posterior: plain(PosteriorSettings) | None = keyword("facets, ligaments (none: the disc alone)")
    neutral_step: Bool = keyword("a step without load first: RoM from the neutral position")


def posterior_settings(
    value: PosteriorSettings | dict | None, where: str = "fe/params.yaml"
) -> PosteriorSettings:
    """Validated posterior elements from ``fe.settings.posterior`` (a mapping, an instance, or
    None: the disc alone) of the file ``where``; ConfigError: each problem (the field, what was
    given and what is allowed)."""
    if isinstance(value, PosteriorSettings):
        return value
    try:
        return TypeAdapter(PosteriorSettings).validate_python(value)
    except ValidationError as exc:
        found = problems(exc, prefix=("fe", "settings", "posterior"))
        listing = "\n".join(f"  - {message}" for _, message in found)
        raise ConfigError(
            f"{where}: invalid posterior elements:\n{listing}\nFix the values in {where} "
            "(docs/fe-posterior-elements.md lists every field, its unit and range)."
        ) from None
