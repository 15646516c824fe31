"""Forward-mode tangents without torch's slow shape checks of zero tangents.

Concept
-------
In forward mode (``torch.func.jvp``) an operation between a tensor that carries a tangent and one that does not (a
constant: a Python number, the rays' weights, the data) gets the constant's tangent as an *efficient zero tensor*,
a zero that holds no memory. Torch's zero-tensor kernels of the elementwise products and sums learn their result's
shape and dtype by running the operation on ``meta`` tensors, and the torch this project pins (2.13) registers those
meta kernels in Python, through its reference implementations (``torch._meta_registrations``, ``torch._refs``): some
200 Python calls, 0.3-0.9 ms, for each product with a constant, where the product itself takes microseconds. The
forward fit's Jacobian (:mod:`place_safe.calibration.forward_fit`, ``vmap`` over ``jvp`` of the forward model) makes
thousands of them.

:func:`quick_zero_tangents` registers, for as long as it is entered, meta kernels for ``mul``, ``add``, ``sub`` and
``div`` (``Tensor`` overloads) that give the broadcast shape and the promoted dtype directly, the two things the
zero-tensor kernels take from them, and removes them on leaving (the dispatcher then holds torch's own again). The
tangents are the same numbers: the meta kernels decide no value. Measured (docs/results.md, "The forward fit's
Jacobian without torch's slow zero tangents"): the forward fit of a 150-frame level sweep, the same parameters bit for
bit, 22 % less CPU.

Meta tensors appear nowhere else in this project's computations; while the context is entered, other code in the
process that runs these four operations on ``meta`` tensors (``torch.compile``'s fake tensors) gets the same shapes
and dtypes with contiguous strides.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

import numpy as np
import torch

#: The ``aten`` operations whose meta kernels :func:`quick_zero_tangents` registers.
OPERATIONS = ("mul.Tensor", "add.Tensor", "sub.Tensor", "div.Tensor")


def _shape(x) -> tuple:
    """A tensor's shape; a Python number's, ``()`` (for ``np.broadcast_shapes``: a tenth of ``torch.broadcast_shapes``'
    time)."""
    return tuple(x.shape) if isinstance(x, torch.Tensor) else ()


def _broadcast_meta(a, b, *, alpha=1) -> torch.Tensor:
    """The result of an elementwise ``a op b`` (tensors or numbers: broadcast shape, promoted dtype) as an empty meta
    tensor."""
    return torch.empty(np.broadcast_shapes(_shape(a), _shape(b)), dtype=torch.result_type(a, b), device="meta")


def _division_meta(a, b) -> torch.Tensor:
    """:func:`_broadcast_meta` of a true division: integer operands give the default floating dtype."""
    out = _broadcast_meta(a, b)
    return out if out.dtype.is_floating_point or out.dtype.is_complex else out.to(torch.get_default_dtype())


@contextmanager
def quick_zero_tangents() -> Iterator[None]:
    """Within it, products and sums with constants in forward mode skip torch's Python meta kernels (module doc)."""
    lib = torch.library.Library("aten", "IMPL", "Meta")
    try:
        for op in OPERATIONS:
            lib.impl(op, _division_meta if op.startswith("div") else _broadcast_meta)
        yield
    finally:
        lib._destroy()


__all__ = ["quick_zero_tangents", "OPERATIONS"]
