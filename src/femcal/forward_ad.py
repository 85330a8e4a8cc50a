"""Constants in forward-mode automatic differentiation.

PyTorch stands in an efficient zero tensor for a missing forward-mode tangent, and that tensor's
kernels work out each result's shape through Python meta functions (pytorch/pytorch#69687): an
operation between a dual tensor and a plain constant costs ~250 us instead of ~10 us on the CPU
(torch 2.13). The effects' parameter derivatives
(:func:`femcal.effects.jacobian.parameter_partials`) run the effects' laws on dual tensors;
:func:`constant_like` gives their constants an explicit zero tangent instead.
"""

from __future__ import annotations

import torch
import torch.autograd.forward_ad as fwad


def has_tangent(t: torch.Tensor) -> bool:
    """Whether ``t`` carries a forward-mode tangent (a dual tensor at the current level)."""
    return fwad.unpack_dual(t).tangent is not None


def constant_like(x: float | torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``x`` as a tensor of ``like``'s dtype and device, with a zero tangent when ``like`` is a
    dual tensor (unchanged otherwise, or when ``x`` carries a tangent of its own).

    Parameters
    ----------
    x : float or Tensor, any shape
    like : Tensor

    Returns
    -------
    Tensor, the shape of ``x``
    """
    t = torch.as_tensor(x, dtype=like.dtype, device=like.device)
    if not has_tangent(like) or has_tangent(t):
        return t
    t = t.contiguous()  # an expanded tensor cannot carry a tangent
    return fwad.make_dual(t, torch.zeros_like(t))
