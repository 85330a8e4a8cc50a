"""The built-in effects: facet contact, ligament tension, neutral-zone laxity.

Each is a law family, not a single formula: a shape parameter spans its phenomenon's usual
forms, and starts at the family's classic member (so a calibration starts from that law and
bends it only when the data ask for it; the extra parameter pays its BIC penalty in the
diagnosis like any other):

* facet contact, ``M = k (phi - gap)_+^n`` with ``n`` in [1, 3]: a linear spring after the gap
  (n = 1), Hertz-like contact (n = 1.5), the classic quadratic (n = 2) and stiffer; the corner
  at the gap rounded over an onset width of 0.05 (sharp) to 2 deg (soft engagement), the
  closure counted from the neutral position (no moment there);
* ligament tension, ``M = k (exp((phi - slack)_+ / s) - 1)`` with the toe length ``s`` in
  [0.5, 8] deg: a long toe region that is nearly linear (large ``s``) to an abrupt lock-up;
* neutral-zone laxity, ``phi = range (1 - exp(-(M / m0)^b))`` with ``b`` in [0.5, 3]: a slow
  saturating laxity (b < 1), the classic exponential (b = 1) to a sigmoid that flattens
  abruptly (b > 1).

Where each engages and how stiff it is may differ per load case (``per_load_case``): facets
are compressed in extension and impinge in axial rotation; the supraspinous, interspinous and
flavum ligaments resist flexion, the intertransverse ligaments lateral bending; the neutral
zone differs per plane. Their split forms (``facet_contact:split``, ...,
:mod:`femcal.effects.split`) give gap, slack, stiffness and laxity one value per load case; the
shape of the law stays shared.

Where each may act is a prior per load case (``load_case_prior``); the registered form acts
in the likely load cases (prior >= 0.5), and the diagnosis fits the other allowed load cases
too, each priced by the prior (:mod:`femcal.effects.terms`):

* facets: extension and axial rotation 0.9 (the articular surfaces are compressed in extension
  and the contralateral facet impinges in axial rotation: Adams & Hutton 1980, Sharma et al.
  1995), lateral bending 0.3 (the ipsilateral facet is loaded in lateral bending, less and not
  in every specimen: Schendel et al. 1993, J Biomech 26:427, measured facet forces in lateral
  bending; Inoue et al. 2020, Spine Surg Relat Res 4:1, review the facet's load in each
  motion); flexion 0 (the facets separate);
* ligaments: flexion and lateral bending 0.9 (supraspinous, interspinous and flavum ligaments
  in flexion, intertransverse ligaments on the convex side in lateral bending: Heuer et al.
  2007, Panjabi et al. 1992), extension 0.3 (the facet capsules are also strained in extension,
  less than in flexion: Ianuzzi et al. 2004, Spine J 4:141); axial rotation 0 (the capsules'
  share there is the facets' contact, which facet contact models);
* neutral-zone laxity: 1 in every load case (every plane has a neutral zone, of its own size:
  Panjabi 1992).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from femcal.effects.base import Effect, EffectParameter, register_effect


def _smooth_ramp(x: torch.Tensor, width: float) -> torch.Tensor:
    """max(x, 0) with its corner rounded over ``width`` (differentiable everywhere):
    ``width * softplus(x / width)``."""
    return torch.nn.functional.softplus(x, beta=1.0 / width)


def _like(p: Mapping[str, torch.Tensor], name: str, ref: torch.Tensor) -> torch.Tensor:
    """Parameter ``name`` (B,) reshaped to broadcast over ``ref`` (B, ...)."""
    return p[name].reshape(-1, *([1] * (ref.ndim - 1)))


@register_effect
class FacetContact(Effect):
    """Facet joints engage in extension and axial rotation (possibly in lateral bending): once
    the rotation closes a gap, contact carries a moment ``M = k * (phi - gap)_+^n`` (n = 1
    linear spring .. 3), the corner at the gap rounded over ``onset`` degrees
    (``w softplus(x / w)``)."""

    name = "facet_contact"
    kind = "parallel"
    load_case_prior = {"Extension": 0.9, "AxialRotation": 0.9, "LateralBending": 0.3}
    parameters = (
        EffectParameter("facet_gap_deg", "deg", 0.0, 6.0, start=1.0, per_load_case=True),
        EffectParameter(
            "facet_stiffness", "Nm/deg^n", 1e-4, 5.0, log=True, start=0.0, per_load_case=True
        ),
        EffectParameter("facet_exponent", "1", 1.0, 3.0, start=0.5, grid=False),
        # How gradually contact engages: the width of the rounded corner at the gap (start:
        # 0.05 deg, a sharp onset; up to 2 deg, cartilage-like soft engagement).
        EffectParameter("facet_onset_deg", "deg", 0.05, 2.0, log=True, start=0.0, grid=False),
    )

    def moment(self, rotation_deg: torch.Tensor, p: Mapping[str, torch.Tensor]) -> torch.Tensor:
        gap = _like(p, "facet_gap_deg", rotation_deg)
        k = _like(p, "facet_stiffness", rotation_deg)
        n = _like(p, "facet_exponent", rotation_deg)
        w = _like(p, "facet_onset_deg", rotation_deg)

        # The closure since the neutral position, its corner at the gap rounded over w: the
        # rounded corner's value at zero rotation is subtracted, so that contact carries no
        # moment in the neutral position (a soft onset over a small gap used to preload the
        # facets, beyond the applied moment for 0.45 % of the box) and its stiffness there
        # stays that of the ramp's slope, not k n (w ln 2)^(n - 1).
        closure = w * (
            torch.nn.functional.softplus((rotation_deg - gap) / w)
            - torch.nn.functional.softplus(-gap / w)
        )
        # closure^n = exp(n log closure), smooth in the closure and n; floored so that far from
        # contact (where softplus underflows to 0) the derivative in n is 0, not 0 * log 0.
        return k * torch.exp(n * torch.log(closure.clamp_min(1e-12)))


@register_effect
class LigamentTension(Effect):
    """Posterior ligaments tighten in flexion and lateral bending (the facet capsules possibly
    in extension): beyond a slack angle they
    carry ``M = k * (exp((phi - slack)_+ / s) - 1)``, a toe region of length ``s`` that stiffens
    exponentially."""

    name = "ligament_tension"
    kind = "parallel"
    load_case_prior = {"Flexion": 0.9, "LateralBending": 0.9, "Extension": 0.3}
    parameters = (
        EffectParameter("ligament_slack_deg", "deg", 0.0, 12.0, start=1.0, per_load_case=True),
        EffectParameter(
            "ligament_stiffness", "Nm", 1e-4, 3.0, log=True, start=0.0, per_load_case=True
        ),
        # start: s = 1.5 deg, the classic member (0.5 * 16 ** u = 1.5).
        EffectParameter("ligament_toe_deg", "deg", 0.5, 8.0, log=True, start=0.3962406, grid=False),
    )

    def moment(self, rotation_deg: torch.Tensor, p: Mapping[str, torch.Tensor]) -> torch.Tensor:
        slack = _like(p, "ligament_slack_deg", rotation_deg)
        k = _like(p, "ligament_stiffness", rotation_deg)
        toe = _like(p, "ligament_toe_deg", rotation_deg)
        stretch = (_smooth_ramp(rotation_deg - slack, 0.05) - _smooth_ramp(-slack, 0.05)) / toe
        # no tension in the neutral position (the rounded corner's value there subtracted)
        return k * torch.expm1(stretch.clamp(max=30.0))


@register_effect
class NeutralZone(Effect):
    """Neutral-zone laxity: extra rotation at low moments that saturates,
    ``phi_nz = range * (1 - exp(-(M / m0)^b))``, in every load case."""

    name = "neutral_zone"
    kind = "series"
    load_case_prior = {
        "Flexion": 1.0,
        "Extension": 1.0,
        "LateralBending": 1.0,
        "AxialRotation": 1.0,
    }
    parameters = (
        EffectParameter("nz_range_deg", "deg", 0.0, 3.0, start=0.0, per_load_case=True),
        EffectParameter("nz_moment_nm", "Nm", 0.1, 1.5, log=True, per_load_case=True),
        # start: b = 1, the classic exponential (0.5 * 6 ** u = 1).
        EffectParameter("nz_shape", "1", 0.5, 3.0, log=True, start=0.3868528, grid=False),
    )

    def rotation(self, moment_nm: torch.Tensor, p: Mapping[str, torch.Tensor]) -> torch.Tensor:
        a = _like(p, "nz_range_deg", moment_nm)
        m0 = _like(p, "nz_moment_nm", moment_nm)
        b = _like(p, "nz_shape", moment_nm)
        return a * (1.0 - torch.exp(-((moment_nm / m0) ** b)))
