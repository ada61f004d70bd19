"""The networks: tanh multilayer perceptrons with a linear output (PyTorch, imported lazily).

``mlp((259, 64, 64, 2))`` is ``Linear(259, 64) -> tanh -> Linear(64, 64) -> tanh ->
Linear(64, 2)``; the paper's network is ``mlp((256, 16, 2))`` (Matlab's default
``tansig`` hidden layer and ``purelin`` output). :func:`layers_of` returns the weights as
numpy ``[(W (in, out), b (out,)), ...]`` for :mod:`.export`, and :func:`forward` runs
those numpy weights (used to check an export without onnxruntime).
"""

from __future__ import annotations

import numpy as np


def mlp(sizes, seed: int = 0):
    """A ``torch.nn.Sequential`` tanh MLP with layer widths ``sizes`` (>= 2 entries).

    Initialisation: PyTorch's default uniform, from ``torch.manual_seed(seed)``.
    """
    import torch

    sizes = [int(s) for s in sizes]
    if len(sizes) < 2 or min(sizes) < 1:
        raise ValueError(f"sizes must be >= 2 positive widths, got {sizes}")
    torch.manual_seed(seed)
    mods = []
    for k, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        mods.append(torch.nn.Linear(a, b))
        if k < len(sizes) - 2:
            mods.append(torch.nn.Tanh())
    return torch.nn.Sequential(*mods)


def linears(net) -> list:
    """The ``torch.nn.Linear`` layers of a :func:`mlp`, in order."""
    import torch
    return [m for m in net if isinstance(m, torch.nn.Linear)]


def sizes_of(net) -> tuple:
    lin = linears(net)
    return tuple([lin[0].in_features] + [m.out_features for m in lin])


def layers_of(net) -> list[tuple[np.ndarray, np.ndarray]]:
    """Numpy weights ``[(W (in, out), b (out,)), ...]`` (float64 copies)."""
    return [(m.weight.detach().cpu().numpy().T.astype(np.float64),
             m.bias.detach().cpu().numpy().astype(np.float64)) for m in linears(net)]


def forward(layers, x: np.ndarray) -> np.ndarray:
    """Run numpy weights on ``(n, in)`` inputs: tanh hidden layers, linear output."""
    h = np.asarray(x, dtype=np.float64)
    for k, (w, b) in enumerate(layers):
        h = h @ w + b
        if k < len(layers) - 1:
            h = np.tanh(h)
    return h


def n_parameters(sizes) -> int:
    """Weights + biases of an MLP with widths ``sizes`` (4,146 for 256-16-2)."""
    return int(sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:])))


__all__ = ["mlp", "linears", "sizes_of", "layers_of", "forward", "n_parameters"]
