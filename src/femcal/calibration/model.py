"""The disc surrogate as a function of the parameters on a fixed moment grid.

:class:`SurrogateCurveModel` is the :class:`~femcal.curves.CurveModel` of the disc alone: for
a batch of parameter vectors it returns the RoM curves of the four load cases at the measured
moments, shape (n, 4, m). It works in the surrogate network's own unit coordinates ``v`` (its
input space; the box is exactly [0, 1]^d, parameters with positive bounds log-scaled, which
conditions the problem), and converts to physical units at the edges, clipping onto the bounds
in float64 so that a returned configuration is never outside the box, not even by rounding.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import torch

from femcal.curves import CurveModel
from femcal.errors import ConfigError
from femcal.space import ParameterSpace
from femcal.surrogates.romnet import forward_tangents

logger = logging.getLogger(__name__)

_EVAL_BATCH = 16_384


__all__ = ["CurveModel", "SurrogateCurveModel"]


class SurrogateCurveModel:
    """A differentiable surrogate evaluated on a moment grid (a :class:`CurveModel`).

    Parameters
    ----------
    surrogate : object
        A fitted femcal surrogate with ``torch_module()`` returning a
        :class:`~femcal.surrogates.romnet.RomNet` (the registered neural surrogate).
    moments : array_like, shape (m,)
        The moment grid in Nm (> 0).
    space : ParameterSpace, optional
        The calibration bounds; the surrogate's own space by default.

    Attributes
    ----------
    net : RomNet
        The frozen network.
    moments : Tensor, shape (m,)
    space : ParameterSpace
    dim : int
        Number of parameters d.
    """

    def __init__(
        self,
        surrogate: object,
        moments: Sequence[float] | np.ndarray,
        *,
        space: ParameterSpace | None = None,
    ) -> None:
        module = getattr(surrogate, "torch_module", None)
        if module is None:
            raise ConfigError(
                f"Calibration needs a differentiable surrogate with torch_module(); got "
                f"{type(surrogate).__name__}. Register a neural surrogate ('nn')."
            )
        self.net = module()
        if not hasattr(self.net, "curves_jacobian"):
            raise ConfigError(
                f"The surrogate's torch module {type(self.net).__name__} has no curves_jacobian; "
                "calibration supports femcal's RomNet."
            )
        self.surrogate = surrogate
        self.space = space if space is not None else surrogate.space  # type: ignore[attr-defined]
        if tuple(self.space.names) != tuple(surrogate.space.names):  # type: ignore[attr-defined]
            raise ConfigError(
                "The calibration space and the surrogate's space name different parameters: "
                f"{list(self.space.names)} vs {list(surrogate.space.names)}."  # type: ignore
            )
        m = np.asarray(moments, dtype=float).reshape(-1)
        if m.size == 0 or np.any(~np.isfinite(m)) or np.any(m <= 0):
            raise ConfigError(f"The moment grid must be finite and > 0; got {m.tolist()}.")
        self.moments = torch.tensor(m, dtype=torch.float32)
        self.dim = self.space.dim
        self.n_evaluations = 0
        self._unit_space: ParameterSpace | None = None

    # ----------------------------------------------------------------- coordinates
    @property
    def unit_space(self) -> ParameterSpace:
        """The coordinates ``v`` the calibrators move in: the network's input space (its
        bounds and scales, :attr:`~femcal.surrogates.romnet.RomNet.space`) under the
        parameters' names."""
        if self._unit_space is None:
            net_space = self.net.space
            self._unit_space = ParameterSpace(
                self.surrogate.space.names,  # type: ignore[attr-defined]
                net_space.lower,
                net_space.upper,
                self.surrogate.space.units,  # type: ignore[attr-defined]
                net_space.scales,
            )
        return self._unit_space

    def to_physical(self, v: np.ndarray | torch.Tensor) -> np.ndarray:
        """Network coordinates (n, d) -> physical parameters (n, d), float64, inside the box."""
        v64 = np.clip(np.asarray(v, dtype=float), 0.0, 1.0)
        return self.space.clip(self.unit_space.from_unit(v64))

    def from_physical(self, x: np.ndarray, *, clip: bool = True) -> torch.Tensor:
        """Physical parameters (n, d) -> network coordinates (n, d), float32.

        With ``clip=False`` points outside the box stay outside (positive parameters are
        floored at 1e-12 so that their logarithm exists); used to evaluate unprojected
        ablations where they stand.
        """
        x = np.asarray(x, dtype=float)
        if not clip:
            x = np.where(self.unit_space.is_log, np.maximum(x, 1e-12), x)
        # torch.tensor copies (x may be a read-only view; as_tensor warned "not writable")
        v = self.unit_space.to_unit(torch.tensor(x, dtype=torch.float32))
        return v.clamp(0.0, 1.0) if clip else v

    def from_linear_unit(self, u: torch.Tensor) -> torch.Tensor:
        """The study's min-max unit box (n, d) -> network coordinates (differentiable).

        Values outside [0, 1] map outside the box too (used by the ablations without
        projection); positive parameters pushed below zero are floored at 1e-12 physical.
        """
        x = self.space.linear().from_unit(u)
        mask = torch.tensor(np.array(self.unit_space.is_log))
        x = torch.where(mask, x.clamp_min(1e-12), x)
        return self.unit_space.to_unit(x)

    def linear_unit_to_physical(self, u: np.ndarray) -> np.ndarray:
        """The study's unit box -> physical, float64, not clipped (ablations report exceedance)."""
        return self.space.linear().from_unit(u)

    # ----------------------------------------------------------------- evaluation
    def curves(self, v: torch.Tensor) -> torch.Tensor:
        """RoM curves, shape (n, d) -> (n, 4, m); differentiable in ``v``."""
        self.n_evaluations += int(v.shape[0])
        return self.net.curves(v, self.moments)

    def curves_jacobian(
        self, v: torch.Tensor, *, jacobian_members: int | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Curves (n, 4, m) and their Jacobian (n, 4, m, d) in network coordinates.

        ``jacobian_members`` differentiates only the first k ensemble members: the values are
        the ensemble's, the Jacobian the mean of those members' (approximate, about
        ``n_members / k`` times cheaper). Default: exact
        (:meth:`~femcal.surrogates.romnet.RomNet.curves_jacobian`).
        """
        self.n_evaluations += int(v.shape[0]) * (1 + self.dim)
        net = self.net
        k_jac = min(int(jacobian_members or net.n_members), net.n_members)
        if k_jac == net.n_members:
            return net.curves_jacobian(v, self.moments)
        # Values from every member, the Jacobian from the first k_jac only (their mean
        # estimates the ensemble's); forward-mode as in RomNet.curves_jacobian.
        basis = net.moment_basis(self.moments)
        n, d = v.shape
        shape = (n, net.n_load_cases, net.moment_degree + 1)
        values = v.new_zeros((n, net.n_load_cases, len(self.moments)))
        jac = v.new_zeros((n, d, net.n_load_cases, len(self.moments)))
        with torch.no_grad():
            for k, member in enumerate(net.members):
                if k >= k_jac:
                    values += net.to_degrees(member(v).reshape(shape) @ basis.T)
                    continue
                h, tangent = forward_tangents(member, v)
                deg = net.to_degrees(h.reshape(shape) @ basis.T)
                dscaled = tangent.reshape(n, d, *shape[1:]) @ basis.T
                scale = deg * net.y_scale if net.log_target else net.y_scale
                values += deg
                jac += dscaled * (scale[:, None] if net.log_target else scale)
        return values / net.n_members, (jac / k_jac).permute(0, 2, 3, 1)

    def predict(self, x: np.ndarray, *, clip: bool = True) -> np.ndarray:
        """RoM curves of physical configurations, shape (n, d) -> (n, 4, m), float64.

        ``clip=False`` evaluates points outside the box where they are (extrapolation).
        """
        v = self.from_physical(np.asarray(x, dtype=float).reshape(-1, self.dim), clip=clip)
        out = []
        with torch.no_grad():
            for start in range(0, v.shape[0], _EVAL_BATCH):
                out.append(self.net.curves(v[start : start + _EVAL_BATCH], self.moments))
        if not out:
            return np.zeros((0, 4, len(self.moments)))
        return torch.cat(out).double().numpy()
