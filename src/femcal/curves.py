"""What calibration and diagnosis need of a differentiable model: the :class:`CurveModel` protocol.

A curve model gives, for a batch of parameter vectors, the RoM curves of the four load cases on
a fixed moment grid, and their Jacobian. It moves in unit coordinates ``v`` (its
:attr:`~CurveModel.unit_space`, the box [0, 1]^dim, each parameter on its own scale) and
converts to physical units at the edges. Two implementations ship:

* :class:`femcal.calibration.model.SurrogateCurveModel`: the disc surrogate alone;
* :class:`femcal.effects.composite.EffectModel`: the disc surrogate with physical effects.

Every calibrator (:mod:`femcal.calibration`) and the diagnosis (:mod:`femcal.diagnose`) take
any object with this interface.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:
    import numpy as np
    import torch

    from femcal.space import ParameterSpace


@runtime_checkable
class CurveModel(Protocol):
    """A differentiable model of RoM curves on a moment grid.

    Attributes
    ----------
    space : ParameterSpace
        Physical bounds of the parameters (what :meth:`to_physical` clips onto).
    unit_space : ParameterSpace
        The coordinates ``v``: the same parameters with the scales the model moves in.
    moments : Tensor, shape (m,)
        The moment grid in Nm.
    dim : int
        Number of parameters d.
    n_evaluations : int
        Curves evaluated so far (a Jacobian row counts ``1 + d``).
    """

    space: ParameterSpace
    unit_space: ParameterSpace
    moments: torch.Tensor
    dim: int
    n_evaluations: int

    def curves(self, v: torch.Tensor) -> torch.Tensor:
        """RoM curves in degrees, shape (n, d) -> (n, 4, m); differentiable in ``v``."""
        ...

    def curves_jacobian(
        self, v: torch.Tensor, *, jacobian_members: int | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Curves (n, 4, m) and their Jacobian in ``v`` (n, 4, m, d)."""
        ...

    def to_physical(self, v: np.ndarray | torch.Tensor) -> np.ndarray:
        """Unit coordinates (n, d) -> physical parameters (n, d), float64, inside the box."""
        ...

    def from_physical(self, x: np.ndarray, *, clip: bool = True) -> torch.Tensor:
        """Physical parameters (n, d) -> unit coordinates (n, d)."""
        ...

    def predict(self, x: np.ndarray, *, clip: bool = True) -> np.ndarray:
        """RoM curves of physical configurations, shape (n, d) -> (n, 4, m), float64."""
        ...
