"""``einsum2``: torch.einsum of two operands whose batching rule folds vmap's tangents into the contraction. Its
values and every derivative (jvp, vmap over jvp with either or both operands batched, backward) against
``torch.einsum``'s own."""

import pytest
import torch
from torch.func import jacfwd, jvp, vmap

from place_safe.recovery.tangent_einsum import einsum2, many_tangents, many_tangents_active


@pytest.fixture
def written_out():
    """einsum2's own rules: within many_tangents, as the forward fit's Jacobian runs it."""
    with many_tangents():
        yield

#: The equations the forward model uses (convolution matrices per zone, per frame, shared; the zones' crosstalk; the
#: soft binning's rays), each with its operands' shapes.
CASES = [("bzk,znk->bzn", (3, 9, 7), (9, 7, 7)), ("bzk,bnk->bzn", (3, 9, 7), (3, 7, 7)),
         ("bzk,nk->bzn", (3, 9, 7), (7, 7)), ("tf,bfn->btn", (9, 9), (3, 9, 7)),
         ("bzr,bzrn->bzn", (3, 9, 5), (3, 9, 5, 7))]


def _operands(shapes, seed):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(s, dtype=torch.float64, generator=g) for s in shapes]


@pytest.mark.usefixtures("written_out")
@pytest.mark.parametrize("equation, x_shape, m_shape", CASES)
def test_values_and_derivatives_are_einsums(equation, x_shape, m_shape):
    x, m = _operands((x_shape, m_shape), 1)
    dx, dm = _operands((x_shape, m_shape), 2)
    torch.testing.assert_close(einsum2(equation, x, m), torch.einsum(equation, x, m), rtol=1e-14, atol=1e-14)
    with torch.no_grad():
        torch.testing.assert_close(einsum2(equation, x, m), torch.einsum(equation, x, m))
    # forward mode: one operand's tangent, then both
    def ours(a, b):
        return einsum2(equation, a, b)

    def theirs(a, b):
        return torch.einsum(equation, a, b)

    for tangents in ((dx, torch.zeros_like(m)), (torch.zeros_like(x), dm), (dx, dm)):
        torch.testing.assert_close(jvp(ours, (x, m), tangents)[1], jvp(theirs, (x, m), tangents)[1],
                                   rtol=1e-13, atol=1e-13)
    # reverse mode
    xr, mr = x.clone().requires_grad_(), m.clone().requires_grad_()
    out = einsum2(equation, xr, mr)
    w = torch.randn(out.shape, dtype=torch.float64)
    got = torch.autograd.grad((out * w).sum(), (xr, mr))
    want = torch.autograd.grad((torch.einsum(equation, xr, mr) * w).sum(), (xr, mr))
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=1e-13, atol=1e-13)
    assert torch.autograd.gradcheck(lambda a, b: einsum2(equation, a, b), (xr, mr))


@pytest.mark.usefixtures("written_out")
@pytest.mark.parametrize("equation, x_shape, m_shape", CASES)
@pytest.mark.parametrize("batched", ["x", "m", "both"])
def test_many_tangents_at_once_under_vmap(equation, x_shape, m_shape, batched):
    """vmap over jvp (the forward fit's Jacobian) with the tangents of x, of m, or of both batched (four at once)."""
    x, m = _operands((x_shape, m_shape), 3)
    dx = torch.randn((4,) + x_shape, dtype=torch.float64)
    dm = torch.randn((4,) + m_shape, dtype=torch.float64)

    def push(f):
        if batched == "x":
            return vmap(lambda t: jvp(lambda a: f(equation, a, m), (x,), (t,))[1])(dx)
        if batched == "m":
            return vmap(lambda t: jvp(lambda b: f(equation, x, b), (m,), (t,))[1])(dm)
        return vmap(lambda s, t: jvp(lambda a, b: f(equation, a, b), (x, m), (s, t))[1])(dx, dm)

    torch.testing.assert_close(push(einsum2), push(torch.einsum), rtol=1e-13, atol=1e-13)
    # vmap of the einsum itself (the primal batched), batch dimension not first
    xs = torch.randn(x_shape + (4,), dtype=torch.float64)
    torch.testing.assert_close(vmap(lambda a: einsum2(equation, a, m), in_dims=-1)(xs),
                               torch.stack([torch.einsum(equation, xs[..., i], m) for i in range(4)]))


def test_outside_the_fits_block_it_is_plain_torch_and_every_order_works():
    """Outside many_tangents einsum2 is torch.einsum: second-order forward mode and double backward work (within it,
    torch reads a written-out jvp as the end of forward mode, and the custom op has no backward of its own)."""
    assert not many_tangents_active()
    q = torch.tensor([1.0, 2.0], dtype=torch.float64)
    torch.testing.assert_close(jacfwd(jacfwd(lambda v: einsum2("i,i->", v, v)))(q),
                               2.0 * torch.eye(2, dtype=torch.float64))
    x = q.clone().requires_grad_()
    (g,) = torch.autograd.grad(einsum2("i,i->", x, x), x, create_graph=True)
    (h,) = torch.autograd.grad(g.sum(), x)
    torch.testing.assert_close(h, torch.full((2,), 2.0, dtype=torch.float64))
    with many_tangents():
        with many_tangents():
            assert many_tangents_active()
        assert many_tangents_active()
    assert not many_tangents_active()


@pytest.mark.parametrize("equation", ["bzk,znk", "bzk->bzn", "bzk,znk,z->bzn", "bzz,znk->bzn", "bzq,znk->bzn",
                                      "bzk,znk->bzq", "bZk,Znk->bZn"])
def test_an_equation_it_cannot_take_is_refused_at_once(equation):
    """Equations whose backward or batching rule would break (no result, three operands, a repeated index, an index in
    one place only, uppercase letters, which the batching rule uses) are refused when called, not later in backward."""
    x, m = torch.ones(2, 9, 3, dtype=torch.float64), torch.ones(9, 3, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="einsum2 takes"):
        einsum2(equation, x, m)
