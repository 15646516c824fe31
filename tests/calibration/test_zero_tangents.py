"""Forward-mode tangents with quick zero-tangent shape checks: the same numbers, and torch as it was afterwards."""

import pytest
import torch
from torch.func import jvp, vmap

from place_safe.calibration.zero_tangents import OPERATIONS, quick_zero_tangents


def _dumps() -> list[str]:
    return [torch._C._dispatch_dump(f"aten::{op}") for op in OPERATIONS]


def _model(p: torch.Tensor) -> torch.Tensor:
    """Products, sums, differences and quotients of ``p`` with constants of every kind: Python numbers, 0-d tensors,
    broadcast tensors, integers."""
    w = torch.linspace(0.5, 1.5, 7, dtype=torch.float64)
    k = torch.arange(1, 8)  # integers
    y = 2.0 * p * p - 1.0
    y = y * w + torch.tensor(0.25, dtype=torch.float64)
    y = (y - w.view(1, 7)) / (p * 3.0 + k)
    return torch.exp(-y) + y / 2 - 7


def test_tangents_are_the_same_numbers_and_torch_is_restored():
    p = torch.linspace(0.2, 1.2, 21, dtype=torch.float64).view(3, 7)
    tangents = torch.randn(5, 3, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(0))

    def run():
        return vmap(lambda t: jvp(_model, (p,), (t,))[1])(tangents), jvp(_model, (p,), (tangents[0],))

    before = _dumps()
    want_v, (want_y, want_t) = run()
    with quick_zero_tangents():
        assert _dumps() != before  # our kernels are in
        got_v, (got_y, got_t) = run()
    assert _dumps() == before
    for got, want in ((got_v, want_v), (got_y, want_y), (got_t, want_t)):
        assert got.dtype == want.dtype and got.shape == want.shape
        assert torch.equal(got, want)


def test_meta_results_keep_torchs_shapes_and_dtypes():
    """The meta kernels give what torch's give: broadcast shape and promoted dtype, wrapped numbers and 0-d tensors
    included, and true division of integers a floating dtype."""
    cases = [(torch.float32, (3, 1), torch.float64, ()), (torch.int64, (2, 3), torch.float32, (3,)),
             (torch.int32, (4,), torch.int64, (4,)), (torch.float64, (2, 1, 5), torch.float32, (3, 1))]
    ops = [torch.mul, torch.add, torch.sub, torch.div]
    want = []
    for da, sa, db, sb in cases:
        a, b = torch.ones(sa, dtype=da, device="meta"), torch.ones(sb, dtype=db, device="meta")
        want.append([(op(a, b).shape, op(a, b).dtype) for op in ops] + [((a * 2.5).shape, (a * 2.5).dtype)])
    with quick_zero_tangents():
        for (da, sa, db, sb), expected in zip(cases, want):
            a, b = torch.ones(sa, dtype=da, device="meta"), torch.ones(sb, dtype=db, device="meta")
            got = [(op(a, b).shape, op(a, b).dtype) for op in ops] + [((a * 2.5).shape, (a * 2.5).dtype)]
            assert got == expected


def test_leaving_on_an_error_restores_torch():
    before = _dumps()
    with pytest.raises(RuntimeError, match="inside"):
        with quick_zero_tangents():
            raise RuntimeError("inside")
    assert _dumps() == before
