"""Torch ``Linear``/``Tanh`` stacks as numpy products: the learned actors' evaluation form.

One agent at a time, as evaluation calls them, numpy products are ~20x cheaper than the torch module's
per-call overhead. Inputs carry a singleton axis before the features (``(..., 1, d) @ (d, h)``, a stacked
matmul): every row's product is then bit for bit that of its own call, which a plain ``(k, d) @ (d, h)`` does
not promise.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

def numpy_layers(layers: Sequence[Any]) -> list[Any] | None:
    """The numpy form of a sequence of torch ``Linear`` and ``Tanh`` layers (float64): per layer (weight (d, h),
    bias (h,)) of a ``Linear`` or None for a ``Tanh``; None if the sequence holds any other layer."""
    import torch

    if not all(isinstance(layer, (torch.nn.Linear, torch.nn.Tanh)) for layer in layers):
        return None
    return [(layer.weight.detach().numpy().astype(np.float64).T, layer.bias.detach().numpy().astype(np.float64))
            if isinstance(layer, torch.nn.Linear) else None for layer in layers]


def apply_numpy_layers(steps: Sequence[Any], hidden: np.ndarray) -> np.ndarray:
    """``hidden`` (..., 1, d) through the layers of :func:`numpy_layers`."""
    for step in steps:
        hidden = np.tanh(hidden) if step is None else hidden @ step[0] + step[1]
    return hidden
