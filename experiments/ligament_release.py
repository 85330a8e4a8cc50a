"""A ligament taut at rest, released in extension: an effect file tried on the FE-made cohort,
not a built-in effect (docs/benchmarks/fe.md, *A release law tried as an effect file*).

A ligament with tension at rest holds the disc turned into extension. In extension it unloads:
the moment it held at rest, ``P``, passes to the applied moment as the rotation takes up its
pre-stretch ``x0``, and stays there once the ligament is slack. The resistance in Nm is
``M = P * (1 - ((x0 - phi)_+ / x0)^2)``: 0 at ``phi = 0`` with stiffness ``2 P / x0``, and
``P`` from ``phi = x0`` on (a saturating law; no built-in law saturates in moment).

Loaded as a user effect module (``effects.modules`` in a ``params.yaml``, or
``femcal diagnose --effects-module experiments/ligament_release.py``); importing it registers
``ligament_release``.
"""

import torch

from femcal.effects import Effect, EffectParameter, register_effect


@register_effect
class LigamentRelease(Effect):
    """A pre-tensioned ligament unloading in extension: a resistance that saturates at P."""

    name = "ligament_release"
    kind = "parallel"
    load_cases = ("Extension",)
    parameters = (
        # start: P at its lower bound, 1e-3 Nm (switched off)
        EffectParameter("release_moment_nm", "Nm", 1e-3, 3.0, log=True, start=0.0),
        EffectParameter("release_angle_deg", "deg", 0.1, 6.0, log=True, start=0.5),
    )

    def moment(self, rotation_deg: torch.Tensor, p) -> torch.Tensor:
        shape = (-1, *([1] * (rotation_deg.ndim - 1)))
        moment = p["release_moment_nm"].reshape(shape)
        angle = p["release_angle_deg"].reshape(shape)
        left = torch.clamp(angle - rotation_deg, min=0.0) / angle
        return moment * (1.0 - left * left)
