"""The surrogate's torch model, :class:`RomNet` (plain torch: no Lightning here).

For one configuration the RoM curve of a load case is very close to a cubic polynomial in the
log-moment in log-RoM space, so :class:`RomNet` maps the parameters (unit box; parameters whose
bounds are strictly positive in log scale) through an MLP to the 4 x 4 coefficients of those
cubics (the estimator: :mod:`femcal.surrogates.nn`; its accuracy: ``reports/surrogates.md``).
:func:`forward_tangents` differentiates a member MLP in forward mode (the curve model's
Jacobian); :func:`ensemble_forward` and :func:`ensemble_tangents` give the same values for all
members at once, without graph. Training with Lightning: :mod:`femcal.surrogates.romnet_training`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES
from femcal.space import ParameterSpace

#: Activation functions by name.
ACTIVATIONS: dict[str, type[nn.Module]] = {
    "silu": nn.SiLU,
    "gelu": nn.GELU,
    "relu": nn.ReLU,
    "tanh": nn.Tanh,
    "softplus": nn.Softplus,
}
#: Learning-rate schedules understood by :class:`RomLightningModule`.
LR_SCHEDULES: tuple[str, ...] = ("onecycle", "cosine", "constant")
#: Loss functions understood by :class:`RomLightningModule`.
LOSSES: tuple[str, ...] = ("l1", "l2")
_SQRT_HALF = math.sqrt(0.5)
#: Buffers of models saved before the input transform moved to ParameterSpace (dropped on load).
_LEGACY_BUFFERS = ("log_mask", "log_lower", "log_upper")
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


def check_activation(activation: str) -> None:
    """Refuse an activation that is not one of :data:`ACTIVATIONS`.

    Parameters
    ----------
    activation : str
        The name of a hidden activation.

    Raises
    ------
    ConfigError
        ``activation`` is not a key of :data:`ACTIVATIONS`; the message lists them.
    """
    if activation not in ACTIVATIONS:
        raise ConfigError(
            f"Unknown activation '{activation}'; choose one of {', '.join(ACTIVATIONS)}."
        )


# ----------------------------------------------------------------------------- the torch model
class RomNet(nn.Module):
    """Differentiable RoM model: (load case, moment, physical parameters) -> RoM in degrees.

    An ensemble of ``n_members`` MLPs sharing one input and output scaling; the output is the
    mean of the members' RoM in degrees.

    Parameters
    ----------
    lower, upper : array_like, shape (d,)
        Parameter bounds in physical units (from the :class:`~femcal.space.ParameterSpace`).
    hidden : sequence of int
        Widths of the hidden layers of each member MLP.
    activation : {"silu", "gelu", "relu", "tanh", "softplus"}
        Hidden activation.
    dropout : float
        Dropout probability after each hidden activation (0 disables it).
    n_members : int
        Number of ensemble members.
    log_target : bool
        Whether the network models log RoM (the output is then ``exp`` of it, always > 0).
    log_params : bool
        Whether parameters with strictly positive bounds enter in log scale (mapped to [0, 1]
        by the log of their bounds); the others are mapped linearly to [0, 1]. The map is
        :attr:`space`'s (:meth:`femcal.space.ParameterSpace.log_where_positive`).
    moment_degree : int
        Degree of the polynomial in the scaled log-moment.
    moment_loc, moment_scale : float
        Scaling of the log-moment: ``z = (log M - moment_loc) / moment_scale``.
    y_loc, y_scale : float
        Output scaling: the members predict ``(t - y_loc) / y_scale`` with ``t`` = log RoM
        (``log_target``) or RoM in degrees.

    names : sequence of str, optional
        Parameter names (``p0``, ``p1``, ... by default), for :attr:`space`.

    Attributes
    ----------
    space : ParameterSpace
        The network's input space: the bounds with each parameter's scale. :meth:`unit` and
        :meth:`params_from_unit` are its :meth:`~femcal.space.ParameterSpace.to_unit` and
        :meth:`~femcal.space.ParameterSpace.from_unit`, in the dtype of their argument.

    Notes
    -----
    The bounds and output scalings are buffers, so ``state_dict`` holds the whole fitted model
    and ``.double()`` gives a float64 model (used to check gradients with
    ``torch.autograd.gradcheck``).
    """

    def __init__(
        self,
        lower: Sequence[float] | np.ndarray,
        upper: Sequence[float] | np.ndarray,
        *,
        hidden: Sequence[int] = (256, 256, 256, 256),
        activation: str = "gelu",
        dropout: float = 0.0,
        n_members: int = 1,
        log_target: bool = True,
        log_params: bool = True,
        moment_degree: int = 3,
        moment_loc: float = 0.0,
        moment_scale: float = 1.0,
        y_loc: float = 0.0,
        y_scale: float = 1.0,
        names: Sequence[str] | None = None,
    ) -> None:
        super().__init__()
        lower_t = torch.tensor(np.array(lower, dtype=float), dtype=torch.float32)
        upper_t = torch.tensor(np.array(upper, dtype=float), dtype=torch.float32)
        if (
            lower_t.ndim != 1
            or lower_t.shape != upper_t.shape
            or not bool(torch.all(lower_t < upper_t))
        ):
            raise ConfigError("RomNet needs 1-D bounds of equal length with lower < upper.")
        check_activation(activation)
        if n_members < 1 or moment_degree < 0 or not 0.0 <= dropout < 1.0:
            raise ConfigError(
                "RomNet needs n_members >= 1, moment_degree >= 0 and 0 <= dropout < 1; got "
                f"{n_members}, {moment_degree}, {dropout}."
            )
        self.n_params = int(lower_t.numel())
        self.hidden = tuple(int(h) for h in hidden)
        self.activation = activation
        self.dropout = float(dropout)
        self.n_members = int(n_members)
        self.log_target = bool(log_target)
        self.log_params = bool(log_params)
        self.moment_degree = int(moment_degree)
        self.n_load_cases = len(LOAD_CASES)

        names = [f"p{j}" for j in range(self.n_params)] if names is None else list(names)
        space = ParameterSpace(names, np.array(lower, dtype=float), np.array(upper, dtype=float))
        self.space = space.log_where_positive() if self.log_params else space
        self.register_buffer("lower", lower_t)
        self.register_buffer("upper", upper_t)
        self.register_buffer("moment_loc", torch.tensor(float(moment_loc)))
        self.register_buffer("moment_scale", torch.tensor(float(moment_scale)))
        self.register_buffer("y_loc", torch.tensor(float(y_loc)))
        self.register_buffer("y_scale", torch.tensor(float(y_scale)))
        self.members = nn.ModuleList([self._make_member() for _ in range(self.n_members)])

    def _make_member(self) -> nn.Sequential:
        layers: list[nn.Module] = []
        width = self.n_params
        for h in self.hidden:
            layers += [nn.Linear(width, h), ACTIVATIONS[self.activation]()]
            if self.dropout > 0:
                layers.append(nn.Dropout(self.dropout))
            width = h
        layers.append(nn.Linear(width, self.n_load_cases * (self.moment_degree + 1)))
        return nn.Sequential(*layers)

    def architecture(self) -> dict[str, Any]:
        """Constructor arguments that rebuild this module (bounds and scalings excluded).

        Returns
        -------
        dict
            hidden, activation, dropout, n_members, log_target, log_params, moment_degree.
        """
        return {
            "hidden": list(self.hidden),
            "activation": self.activation,
            "dropout": self.dropout,
            "n_members": self.n_members,
            "log_target": self.log_target,
            "log_params": self.log_params,
            "moment_degree": self.moment_degree,
        }

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # noqa: D401
        # Models saved before the transform moved to ParameterSpace carry its log bounds as
        # buffers: they are derived from the bounds, so they are dropped on load.
        for key in _LEGACY_BUFFERS:
            state_dict.pop(prefix + key, None)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    # -------------------------------------------------------------------------- pieces
    def unit(self, params: torch.Tensor) -> torch.Tensor:
        """Physical parameters, shape (n, d) -> network inputs in [0, 1] inside the box."""
        return self.space.to_unit(params)

    def moment_basis(self, moment_nm: torch.Tensor) -> torch.Tensor:
        """Polynomial basis of the scaled log-moment, shape (n,) -> (n, moment_degree + 1)."""
        z = (torch.log(moment_nm) - self.moment_loc) / self.moment_scale
        return torch.stack([z**j for j in range(self.moment_degree + 1)], dim=-1)

    def coefficients(self, params: torch.Tensor) -> torch.Tensor:
        """Per-member polynomial coefficients, shape (n, d) -> (n_members, n, 4, degree + 1)."""
        u = self.unit(params)
        shape = (u.shape[0], self.n_load_cases, self.moment_degree + 1)
        return torch.stack([m(u).reshape(shape) for m in self.members])

    def members_scaled(
        self,
        load_case_index: torch.Tensor,
        moment_nm: torch.Tensor,
        params: torch.Tensor,
        group: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Scaled outputs of every member (the quantity the training loss compares).

        Parameters
        ----------
        load_case_index : LongTensor, shape (n,)
            Index into :data:`~femcal.schema.LOAD_CASES`.
        moment_nm : Tensor, shape (n,)
            Moment in Nm, > 0.
        params : Tensor, shape (n, d) or (g, d)
            Physical parameters, one row per row of the batch, or one row per group when
            ``group`` is given.
        group : LongTensor, shape (n,), optional
            Row -> row of ``params``; lets a batch of configurations evaluate each MLP once.

        Returns
        -------
        Tensor, shape (n_members, n)
        """
        coef = self.coefficients(params)  # (K, g, 4, p)
        rows = torch.arange(moment_nm.shape[0], device=moment_nm.device)
        gidx = rows if group is None else group
        picked = coef[:, gidx, load_case_index]  # (K, n, p)
        return (picked * self.moment_basis(moment_nm)).sum(-1)

    def to_degrees(self, scaled: torch.Tensor) -> torch.Tensor:
        """Scaled outputs -> RoM in degrees, any shape."""
        t = scaled * self.y_scale + self.y_loc
        return torch.exp(t) if self.log_target else t

    def members_degrees(
        self,
        load_case_index: torch.Tensor,
        moment_nm: torch.Tensor,
        params: torch.Tensor,
        group: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """RoM of every member in degrees, shape (n_members, n); see :meth:`members_scaled`."""
        return self.to_degrees(self.members_scaled(load_case_index, moment_nm, params, group))

    def forward(
        self, load_case_index: torch.Tensor, moment_nm: torch.Tensor, params: torch.Tensor
    ) -> torch.Tensor:
        """RoM in degrees, the mean of the members, shape (n,).

        The batch as for :meth:`members_scaled`, one row of ``params`` (physical units, shape
        (n, d)) per row.
        """
        return self.members_degrees(load_case_index, moment_nm, params).mean(0)

    # ------------------------------------------------- curves on a grid, for calibration
    def params_from_unit(self, v: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`unit`: network inputs, shape (n, d) -> physical parameters."""
        return self.space.from_unit(v)

    def curves(self, v: torch.Tensor, moment_nm: torch.Tensor) -> torch.Tensor:
        """RoM curves of every load case on a moment grid, from network inputs.

        Parameters
        ----------
        v : Tensor, shape (n, d)
            Parameters in the network's unit coordinates (:meth:`unit`); the box is [0, 1]^d.
        moment_nm : Tensor, shape (m,)
            Moments in Nm, > 0.

        Returns
        -------
        Tensor, shape (n, 4, m)
            RoM in degrees, mean of the members.
        """
        basis = self.moment_basis(moment_nm)  # (m, p)
        shape = (v.shape[0], self.n_load_cases, self.moment_degree + 1)
        out = v.new_zeros((v.shape[0], self.n_load_cases, moment_nm.shape[0]))
        for member in self.members:
            out = out + self.to_degrees(member(v).reshape(shape) @ basis.T)
        return out / self.n_members

    def curves_jacobian(
        self, v: torch.Tensor, moment_nm: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`curves` and its Jacobian in ``v`` by forward-mode differentiation.

        The ``d`` tangents travel through each member as one extra batch dimension, so the
        cost is about ``d + 1`` forward passes of large matrix products (no autograd graph).

        Parameters
        ----------
        v : Tensor, shape (n, d)
            Network inputs (see :meth:`curves`).
        moment_nm : Tensor, shape (m,)
            Moments in Nm.

        Returns
        -------
        values : Tensor, shape (n, 4, m)
            RoM in degrees.
        jacobian : Tensor, shape (n, 4, m, d)
            d RoM / d v.
        """
        basis = self.moment_basis(moment_nm)  # (m, p)
        n, d = v.shape
        n_lc, p = self.n_load_cases, self.moment_degree + 1
        values = v.new_zeros((n, n_lc, moment_nm.shape[0]))
        jac = v.new_zeros((n, d, n_lc, moment_nm.shape[0]))
        with torch.no_grad():
            for member in self.members:
                h, tangent = forward_tangents(member, v)
                scaled = h.reshape(n, n_lc, p) @ basis.T  # (n, 4, m)
                dscaled = tangent.reshape(n, d, n_lc, p) @ basis.T  # (n, d, 4, m)
                deg = self.to_degrees(scaled)
                if self.log_target:
                    ddeg = dscaled * (deg * self.y_scale)[:, None]
                else:
                    ddeg = dscaled * self.y_scale
                values += deg
                jac += ddeg
        return values / self.n_members, (jac / self.n_members).permute(0, 2, 3, 1)


def _activation_derivative(module: nn.Module, z: torch.Tensor) -> torch.Tensor:
    """Elementwise derivative of a hidden activation at its input ``z``."""
    if isinstance(module, nn.GELU) and module.approximate == "none":
        return 0.5 * (1.0 + torch.erf(z * _SQRT_HALF)) + z * torch.exp(-0.5 * z * z) * _INV_SQRT_2PI
    if isinstance(module, nn.SiLU):
        sig = torch.sigmoid(z)
        return sig * (1.0 + z * (1.0 - sig))
    if isinstance(module, nn.ReLU):
        return (z > 0).to(z.dtype)
    if isinstance(module, nn.Tanh):
        return 1.0 - torch.tanh(z) ** 2
    if isinstance(module, nn.Softplus) and module.beta == 1:
        return torch.sigmoid(z)
    raise ConfigError(f"No forward-mode rule for activation {module!r}.")


def forward_tangents(member: nn.Sequential, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Output of an MLP member and its Jacobian, shapes (n, out) and (n, d, out).

    Dropout is the identity here (eval mode is assumed).
    """
    h = v
    tangent: torch.Tensor | None = None  # (n, d, width); None = identity
    z: torch.Tensor | None = None
    for layer in member:
        if isinstance(layer, nn.Linear):
            z = layer(h)
            if tangent is None:
                tangent = layer.weight.T.expand(v.shape[0], *layer.weight.T.shape)
            else:
                tangent = tangent @ layer.weight.T
            h = z
        elif isinstance(layer, nn.Dropout):
            continue
        else:
            assert z is not None and tangent is not None
            tangent = tangent * _activation_derivative(layer, z)[:, None, :]
            h = layer(z)
    assert tangent is not None
    return h, tangent


def _member_layers(members: Sequence[nn.Sequential]) -> list[list[nn.Module]]:
    """Each member's layers without its dropouts (the identity in eval mode); ValueError when
    the members differ in their layer types."""
    layers = [[layer for layer in m if not isinstance(layer, nn.Dropout)] for m in members]
    kinds = {tuple(type(layer) for layer in ls) for ls in layers}
    if len(kinds) != 1:
        raise ValueError("The ensemble's members differ in their layers.")
    return layers


def _ensemble_linear(layers, i: int, h: torch.Tensor, shared: bool) -> torch.Tensor:
    """Layer ``i`` (Linear) of every member, (K, n, out): member ``k`` applied to ``h``
    (n, in) if ``shared`` else to ``h[k]``, each computed as :class:`torch.nn.Linear` does."""
    first = layers[0][i]
    out = h.new_empty((len(layers), h.shape[-2], first.out_features))
    for k, member in enumerate(layers):
        layer = member[i]
        if layer.bias is None:
            torch.mm(h if shared else h[k], layer.weight.t(), out=out[k])
        else:
            torch.addmm(layer.bias, h if shared else h[k], layer.weight.t(), out=out[k])
    return out


def ensemble_forward(members: Sequence[nn.Sequential], v: torch.Tensor) -> torch.Tensor:
    """Every member's output at ``v`` (n, d), shape (K, n, out), without graph.

    The same values as ``torch.stack([m(v) for m in members])`` in eval mode, each member's
    linear layers computed alone, the activations of all members at once.
    """
    layers = _member_layers(members)
    h = v
    with torch.no_grad():
        for i, layer in enumerate(layers[0]):
            if isinstance(layer, nn.Linear):
                h = _ensemble_linear(layers, i, h, shared=h is v)
            else:
                h = layer(h)
    return h


def ensemble_tangents(
    members: Sequence[nn.Sequential], v: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Every member's output and Jacobian at ``v`` (n, d): shapes (K, n, out), (K, n, d, out).

    The values of :func:`forward_tangents` for each member (eval mode), without graph; the
    activations and their derivatives of all members computed at once.
    """
    layers = _member_layers(members)
    n_members, n = len(layers), v.shape[0]
    h = v
    tangent: torch.Tensor | None = None  # (K, n, d, width); None = identity
    z: torch.Tensor | None = None
    with torch.no_grad():
        for i, layer in enumerate(layers[0]):
            if isinstance(layer, nn.Linear):
                z = _ensemble_linear(layers, i, h, shared=h is v)
                weights = [member[i].weight.T for member in layers]
                if tangent is None:
                    tangent = torch.stack(weights)[:, None].expand(n_members, n, *weights[0].shape)
                else:
                    t_new = z.new_empty((n_members, n, tangent.shape[2], layer.out_features))
                    for k, w in enumerate(weights):
                        torch.matmul(tangent[k], w, out=t_new[k])
                    tangent = t_new
                h = z
            else:
                assert z is not None and tangent is not None
                tangent = tangent * _activation_derivative(layer, z)[:, :, None, :]
                h = layer(z)
    assert tangent is not None
    return h, tangent
