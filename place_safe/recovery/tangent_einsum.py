"""An einsum of two operands that batches many tangents into its contraction.

Concept
-------
The forward fit's Jacobian (:mod:`place_safe.calibration.forward_fit`) pushes dozens of tangents at once through the
forward model: ``torch.func.vmap`` over ``torch.func.jvp``. Where the model contracts a tangent with an operand that
carries none (a histogram with its pulse's convolution matrix, a ray's amplitude with its soft-binning kernel), the
tangent is batched and the operand is not, and torch's batching rule for ``einsum`` and ``matmul`` copies the operand
once per tangent to make the batch dimensions agree: the convolution matrices 15-32 times, the soft-binning kernel
(frames x zones x rays x bins) as often. Those copies were the largest part of the Jacobian's time.

:func:`einsum2` is ``torch.einsum(equation, x, m)`` with its own batching rule: a batched operand gets a new index of
its own in the equation, which the result then carries (a batch in both shares the one index). The contraction then
runs once over all tangents, as one matrix product, and no operand is copied. Its derivatives in both operands are
written out (it is linear in each), so it works under ``jvp``, ``vmap`` of it and ``backward``.

It acts only within :func:`many_tangents` (the forward fit's Jacobian enters it); elsewhere, and without gradients, it
is ``torch.einsum`` itself, the same values. The other operations of the forward model that write out their
derivatives for many tangents (:func:`~place_safe.recovery.forward.apply_pileup`, the fit's Anscombe residual) read the
same switch. Within it, derivatives of second order are not available: torch takes an ``autograd.Function``'s
written-out ``jvp`` as the end of forward mode (``jacfwd`` of ``jacfwd`` reads 0) and the custom op has no backward of
its own (a second ``backward`` raises); outside it the model is plain torch, and every order works as before.
"""

from __future__ import annotations

from contextlib import contextmanager
from functools import lru_cache
from typing import Iterator

import torch

_DEPTH = [0]  # how many many_tangents() blocks are open (the fit is single-threaded; nesting is allowed)


@contextmanager
def many_tangents() -> Iterator[None]:
    """Within it, :func:`einsum2` and the model's other written-out derivatives act (module doc): for ``vmap`` over
    ``jvp`` with many tangents at once, first order only."""
    _DEPTH[0] += 1
    try:
        yield
    finally:
        _DEPTH[0] -= 1


def many_tangents_active() -> bool:
    """Whether a :func:`many_tangents` block is open."""
    return _DEPTH[0] > 0


#: Letters for the batch index :func:`_batched` adds (the first not already in the equation).
_BATCH_LETTERS = "ABCDEFGHIJKLMNOPQRSTUVWXYZ"


@lru_cache(maxsize=None)
def _sides(equation: str) -> tuple[str, str, str]:
    """The two operands' indices and the result's of ``"a,b->out"``; ValueError for an equation :func:`einsum2` cannot
    take (its backward and batching rule need each index once per operand and every operand's index in the other
    operand or the result)."""
    lhs, arrow, out = equation.partition("->")
    a, comma, b = lhs.partition(",")
    if (not arrow or not comma or "," in b or any(len(set(x)) != len(x) for x in (a, b, out))
            or not set(a) <= set(b) | set(out) or not set(b) <= set(a) | set(out) or not set(out) <= set(a) | set(b)
            or set(equation) - set(_BATCH_LETTERS.lower()) - set(",->")):
        raise ValueError(f"einsum2 takes 'a,b->out' in lowercase letters, each index once per operand and found in the "
                         f"other operand or the result; got {equation!r}")
    return a, b, out


@torch.library.custom_op("place_safe::einsum2", mutates_args=())
def _einsum2(equation: str, x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    return torch.einsum(equation, x, m)


@_einsum2.register_fake
def _(equation, x, m):
    return torch.einsum(equation, x, m)


def _batched(info, in_dims, equation, x, m):
    """:func:`_einsum2` under ``vmap``: each batched operand's batch dimension gets one new index, the result's
    first."""
    _, x_dim, m_dim = in_dims
    a, b, out = _sides(equation)
    letter = next(c for c in _BATCH_LETTERS if c not in equation)
    if x_dim is not None:
        x, a = x.movedim(x_dim, 0), letter + a
    if m_dim is not None:
        m, b = m.movedim(m_dim, 0), letter + b
    return torch.einsum(f"{a},{b}->{letter}{out}", x, m), 0


_einsum2.register_vmap(_batched)


class _Einsum2(torch.autograd.Function):
    """:func:`_einsum2` with its derivatives: the product rule, each term again an :func:`_einsum2`."""

    generate_vmap_rule = True

    @staticmethod
    def forward(equation, x, m):
        return _einsum2(equation, x, m)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.equation = inputs[0]
        ctx.set_materialize_grads(False)  # an operand without a tangent gets None, not a tensor of zeros
        ctx.save_for_backward(inputs[1], inputs[2])
        ctx.save_for_forward(inputs[1], inputs[2])

    @staticmethod
    def jvp(ctx, _d_equation, d_x, d_m):
        x, m = ctx.saved_tensors
        terms = []
        if d_x is not None:
            terms.append(_einsum2(ctx.equation, d_x, m))
        if d_m is not None:
            terms.append(_einsum2(ctx.equation, x, d_m))
        if not terms:
            return torch.zeros(torch.einsum(ctx.equation, x, m).shape, dtype=x.dtype)
        return terms[0] if len(terms) == 1 else terms[0] + terms[1]

    @staticmethod
    def backward(ctx, grad):
        if grad is None:
            return None, None, None
        x, m = ctx.saved_tensors
        a, b, out = _sides(ctx.equation)
        g_x = _einsum2(f"{out},{b}->{a}", grad, m) if ctx.needs_input_grad[1] else None
        g_m = _einsum2(f"{a},{out}->{b}", x, grad) if ctx.needs_input_grad[2] else None
        return None, g_x, g_m


def einsum2(equation: str, x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """``torch.einsum(equation, x, m)`` (two operands, ``"a,b->out"`` in lowercase letters, every index of each operand
    in the other or in the result) that, within :func:`many_tangents`, batches ``vmap``'s tangents into its contraction
    instead of copying the other operand (module doc). Outside it, or without gradients, ``torch.einsum`` itself."""
    _sides(equation)
    if not torch.is_grad_enabled() or not many_tangents_active():
        return torch.einsum(equation, x, m)
    return _Einsum2.apply(equation, x, m)
