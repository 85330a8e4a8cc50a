"""femcal.forward_ad: constants with explicit zero tangents."""

import torch
import torch.autograd.forward_ad as fwad

from femcal.forward_ad import constant_like, has_tangent


def test_a_constant_stays_plain_outside_forward_mode():
    like = torch.ones(3)
    c = constant_like(2.5, like)
    assert not has_tangent(c)
    assert c.dtype == like.dtype and float(c) == 2.5


def test_a_constant_gets_a_zero_tangent_beside_a_dual_tensor():
    with fwad.dual_level():
        x = fwad.make_dual(torch.tensor([1.0, 2.0]), torch.tensor([1.0, 0.5]))
        c = constant_like(torch.tensor([[3.0]]).expand(2, 2), x)  # an expanded constant
        assert has_tangent(c)
        assert torch.equal(fwad.unpack_dual(c).tangent, torch.zeros(2, 2))
        # the derivative of c * x is c * dx, as with a plain constant
        out = fwad.unpack_dual(c * x)
        assert torch.equal(out.tangent, torch.tensor([[3.0, 1.5], [3.0, 1.5]]))


def test_a_dual_input_keeps_its_own_tangent():
    with fwad.dual_level():
        x = fwad.make_dual(torch.tensor([1.0]), torch.tensor([4.0]))
        y = fwad.make_dual(torch.tensor([2.0]), torch.tensor([7.0]))
        assert torch.equal(fwad.unpack_dual(constant_like(y, x)).tangent, torch.tensor([7.0]))
