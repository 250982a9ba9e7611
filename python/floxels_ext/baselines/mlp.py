"""The coordinate MLP used by NSFP and Fast Neural Scene Flow: xyz -> 3D flow.

``num_layers`` counts the activated layers, as in both papers ("8 layers x 128"): a
``Linear(3, W)`` and ``num_layers - 1`` ``Linear(W, W)``, each followed by the activation,
then a linear output head ``Linear(W, 3)``.
"""

from __future__ import annotations

import torch
from torch import nn

ACTIVATIONS = {"relu": nn.ReLU, "sigmoid": nn.Sigmoid, "tanh": nn.Tanh, "leaky_relu": nn.LeakyReLU}
INITS = ("default", "xavier")


class CoordinateMLP(nn.Sequential):
    def __init__(self, num_layers: int = 8, width: int = 128, activation: str = "relu",
                 init: str = "default", seed: int = 0, in_dim: int = 3, out_dim: int = 3) -> None:
        if activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
        if init not in INITS:
            raise ValueError(f"init must be one of {INITS}, got {init!r}")
        if num_layers < 1 or width < 1:
            raise ValueError(f"num_layers and width must be >= 1, got {num_layers}, {width}")
        # Initialise on the CPU from a private RNG stream: the same seed gives the same
        # weights on every device, and the caller's global RNG state is left untouched.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            layers: list[nn.Module] = []
            for i in range(num_layers):
                layers += [nn.Linear(in_dim if i == 0 else width, width), ACTIVATIONS[activation]()]
            layers.append(nn.Linear(width, out_dim))
            super().__init__(*layers)
            if init == "xavier":  # FastNSF's --init_weight: Xavier-uniform weights, zero biases
                for m in self.modules():
                    if isinstance(m, nn.Linear):
                        nn.init.xavier_uniform_(m.weight)
                        nn.init.zeros_(m.bias)
