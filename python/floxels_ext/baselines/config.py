"""Hyperparameters of the NSFP and FastNSF baselines, validated on construction.

Defaults follow the Floxels paper's appendix ("Baseline details and hyperparameters") and the
authors' public code: 8 x 128 ReLU MLP, Adam (NSFP: weight decay 1e-4 as its code applies it,
see NSFPConfig; FastNSF: none), early stopping with
patience 100 / min delta 1e-4, at most 5000 iterations, the result being the flow of the
lowest loss seen.

Learning rates: NSFP's published default is 0.008 (used here); the Floxels paper's appendix
reports 0.0008 for its NSFP runs (pass ``lr=0.0008`` to reproduce that). FastNSF: 0.001.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from floxels_ext.ops.grid import DEFAULT_MAX_CELLS
from floxels_ext.baselines.mlp import ACTIVATIONS, INITS


@dataclass(frozen=True)
class _MLPBaselineConfig:
    # network
    num_layers: int = 8              # activated layers (NSFP-8 / FNSF-8); 16 for "NSFP-16"
    hidden_units: int = 128
    activation: str = "relu"
    init: str = "default"            # "default" (torch.nn.Linear) or "xavier" (FastNSF --init_weight)
    seed: int = 0                    # weight initialisation (and point subsampling) seed
    # optimiser (Adam) and early stopping
    lr: float = 0.008
    adam_betas: tuple[float, float] = (0.9, 0.999)
    adam_eps: float = 1e-8
    weight_decay: float = 0.0
    max_iters: int = 5000
    early_stopping: bool = True      # False = always max_iters iterations (the paper's "*" rows)
    patience: int = 100
    min_delta: float = 1e-4
    # optional random subsampling of both clouds for the optimisation (0 = all points);
    # the flow is still predicted for every source point by the trained MLP
    max_points: int = 0

    def _name(self) -> str:
        return type(self).__name__

    def __post_init__(self) -> None:
        name = self._name()
        for n in ("num_layers", "hidden_units", "max_iters", "patience"):
            v = getattr(self, n)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{name}.{n} must be a positive integer, got {v!r}")
        for n in ("seed", "max_points"):
            v = getattr(self, n)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"{name}.{n} must be an integer >= 0, got {v!r}")
        for n in ("lr", "adam_eps"):
            v = getattr(self, n)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name}.{n} must be a positive finite number, got {v!r}")
        for n in ("weight_decay", "min_delta"):
            v = getattr(self, n)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name}.{n} must be a non-negative finite number, got {v!r}")
        if not isinstance(self.early_stopping, bool):
            raise ValueError(f"{name}.early_stopping must be a bool, got {self.early_stopping!r}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"{name}.activation must be one of {sorted(ACTIVATIONS)}, got {self.activation!r}")
        if self.init not in INITS:
            raise ValueError(f"{name}.init must be one of {INITS}, got {self.init!r}")
        try:
            b1, b2 = self.adam_betas
        except (TypeError, ValueError):
            raise ValueError(f"{name}.adam_betas must be a pair, got {self.adam_betas!r}") from None
        if not (0 <= b1 < 1 and 0 <= b2 < 1):
            raise ValueError(f"{name}.adam_betas must lie in [0, 1), got {self.adam_betas}")

    def replace(self, **changes):
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class NSFPConfig(_MLPBaselineConfig):
    """Neural Scene Flow Prior (Li et al., NeurIPS 2021).

    Loss: ``C(S0 + f(S0), S1) + C(S0 + f(S0) - g(S0 + f(S0)), S0)`` with C the truncated
    Chamfer distance (:func:`floxels_ext.baselines.chamfer.truncated_chamfer`) and g the
    backward-flow MLP (dropped with ``backward_flow=False``).
    """

    lr: float = 0.008
    # The authors' optimization.py builds Adam(param_groups, weight_decay=0) but each of the
    # two parameter groups (forward and backward MLP) carries weight_decay=options.weight_decay,
    # default 1e-4 (config.py), and a group's value overrides the optimiser's: the code decays
    # with 1e-4. (The Floxels appendix says "no weight decay", reading the optimiser's 0.)
    weight_decay: float = 1e-4
    backward_flow: bool = True
    chamfer_truncation: float = 2.0  # NSFP's code zeroes squared NN distances >= 2 (m^2)
    chamfer_squared: bool = True     # False: plain distances, truncated at chamfer_truncation (m)
    nn_chunk_elems: int = 0          # entries of one distance-matrix chunk (0: 2^24 CPU, 2^27 GPU)

    def __post_init__(self) -> None:
        super().__post_init__()
        if not isinstance(self.backward_flow, bool) or not isinstance(self.chamfer_squared, bool):
            raise ValueError("NSFPConfig.backward_flow and chamfer_squared must be bools")
        v = self.chamfer_truncation
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 and not math.isnan(v)):
            raise ValueError(f"NSFPConfig.chamfer_truncation must be positive (inf = no truncation), got {v!r}")
        if not isinstance(self.nn_chunk_elems, int) or isinstance(self.nn_chunk_elems, bool) or self.nn_chunk_elems < 0:
            raise ValueError(f"NSFPConfig.nn_chunk_elems must be an integer >= 0 (0 = per-device default), "
                             f"got {self.nn_chunk_elems!r}")


@dataclass(frozen=True)
class FastNSFConfig(_MLPBaselineConfig):
    """Fast Neural Scene Flow (Li et al., ICCV 2023): the same MLP trained against a distance
    transform of the next scan, ``mean_i DT_{S1}(p_i + f(p_i))`` (correspondence-free).

    The DT is exact (our EDT op) on a ``dt_cell`` lattice covering both scans plus
    ``dt_padding``; look-ups are trilinear with border clamping (our fused ``dt_loss`` op).
    """

    lr: float = 0.001
    dt_cell: float = 0.1             # FastNSF grid_factor 10 -> 0.1 m cells
    dt_padding: float = 0.5          # margin (m) of the DT lattice around both scans
    truncation: float = math.inf     # FastNSF does not truncate the DT; finite values zero DT >= it
    max_dt_cells: int = DEFAULT_MAX_CELLS

    def __post_init__(self) -> None:
        super().__post_init__()
        v = self.dt_cell
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"FastNSFConfig.dt_cell must be a positive finite number, got {v!r}")
        v = self.dt_padding
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
            raise ValueError(f"FastNSFConfig.dt_padding must be a non-negative finite number, got {v!r}")
        v = self.truncation
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 and not math.isnan(v)):
            raise ValueError(f"FastNSFConfig.truncation must be positive (inf = none), got {v!r}")
        if not isinstance(self.max_dt_cells, int) or self.max_dt_cells < 1:
            raise ValueError(f"FastNSFConfig.max_dt_cells must be a positive integer, got {self.max_dt_cells!r}")
