"""The built-in effects: facet contact, ligament tension, neutral-zone laxity."""

from __future__ import annotations

from collections.abc import Mapping

import torch

from femcal.effects.base import Effect, EffectParameter, register_effect


def _smooth_ramp(x: torch.Tensor, width: float) -> torch.Tensor:
    """max(x, 0) with its corner rounded over ``width`` (differentiable everywhere)."""
    return width * torch.nn.functional.softplus(x / width)


@register_effect
class FacetContact(Effect):
    """Facet joints engage in extension and axial rotation: once the rotation closes a gap,
    contact carries a moment growing with the square of the penetration,
    ``M = k * (phi - gap)_+^2``."""

    name = "facet_contact"
    kind = "parallel"
    load_cases = ("Extension", "AxialRotation")
    parameters = (
        EffectParameter("facet_gap_deg", "deg", 0.0, 6.0, start=1.0),
        EffectParameter("facet_stiffness", "Nm/deg^2", 1e-4, 5.0, log=True, start=0.0),
    )

    def moment(self, rotation_deg: torch.Tensor, p: Mapping[str, torch.Tensor]) -> torch.Tensor:
        gap = p["facet_gap_deg"].reshape(-1, *([1] * (rotation_deg.ndim - 1)))
        k = p["facet_stiffness"].reshape(gap.shape)
        return k * _smooth_ramp(rotation_deg - gap, 0.05) ** 2


@register_effect
class LigamentTension(Effect):
    """Posterior ligaments tighten in flexion and lateral bending: beyond a slack angle they
    carry an exponentially stiffening moment, ``M = k * (exp((phi - slack)_+ / 1.5 deg) - 1)``."""

    name = "ligament_tension"
    kind = "parallel"
    load_cases = ("Flexion", "LateralBending")
    parameters = (
        EffectParameter("ligament_slack_deg", "deg", 0.0, 12.0, start=1.0),
        EffectParameter("ligament_stiffness", "Nm", 1e-4, 3.0, log=True, start=0.0),
    )
    scale_deg = 1.5

    def moment(self, rotation_deg: torch.Tensor, p: Mapping[str, torch.Tensor]) -> torch.Tensor:
        slack = p["ligament_slack_deg"].reshape(-1, *([1] * (rotation_deg.ndim - 1)))
        k = p["ligament_stiffness"].reshape(slack.shape)
        stretch = _smooth_ramp(rotation_deg - slack, 0.05) / self.scale_deg
        return k * torch.expm1(stretch.clamp(max=30.0))


@register_effect
class NeutralZone(Effect):
    """Neutral-zone laxity: extra rotation at low moments that saturates,
    ``phi_nz = range * (1 - exp(-M / m0))``, in every load case."""

    name = "neutral_zone"
    kind = "series"
    load_cases = ("Flexion", "Extension", "LateralBending", "AxialRotation")
    parameters = (
        EffectParameter("nz_range_deg", "deg", 0.0, 3.0, start=0.0),
        EffectParameter("nz_moment_nm", "Nm", 0.1, 1.5, log=True),
    )

    def rotation(self, moment_nm: torch.Tensor, p: Mapping[str, torch.Tensor]) -> torch.Tensor:
        a = p["nz_range_deg"].reshape(-1, *([1] * (moment_nm.ndim - 1)))
        m0 = p["nz_moment_nm"].reshape(a.shape)
        return a * (1.0 - torch.exp(-moment_nm / m0))
