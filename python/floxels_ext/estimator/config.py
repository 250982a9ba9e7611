"""Hyperparameters of Floxels (paper defaults) with validation on construction."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from floxels_ext.estimator.config_fields import check_field_types
from floxels_ext.estimator.evidence import EVIDENCE_MODES
from floxels_ext.estimator.evidence_checks import FAR_MODES
from floxels_ext.estimator.config_fields import parse_option_value as _parse_field
from floxels_ext.ops.grid import DEFAULT_MAX_CELLS
from floxels_ext.presets import DEFAULT_NUM_SCANS, PRESETS

__all__ = ["FloxelsConfig", "PRESETS", "parse_option_value"]


@dataclass(frozen=True)
class FloxelsConfig:
    """Every hyperparameter of the method, with the paper's defaults.

    Loss per iteration ``it`` (S = number of support scans, t = time offset of a scan)::

        lambda_d * sum_t w(t) * mean_i DT_t(p_i + t f_i)          (w(t) = 1/t^2, DT >= truncation -> 0)
        + reg_scale * (lambda_c * cluster_loss + lambda_g(it) * mean_i ||f_i||)

    with ``reg_scale = S`` ("support", as in DEVELOPERS.md) or ``2m - 1`` ("paper", the
    factor printed in the paper's final-loss equation), and ``lambda_g`` falling linearly
    from ``lambda_g_start`` to ``lambda_g_end`` over ``lambda_g_decay_iters`` iterations.
    """

    # representation
    voxel_size: float = 0.5          # flow grid spacing (m)
    dt_cell: float = 0.1             # distance-transform sample spacing (m)
    dt_padding: float = 2.0          # margin (m) around each support scan covered by its DT
    truncation: float = 5.0          # DT values >= this count as 0 (no gradient)
    # multi-scan loss
    num_scans: int = DEFAULT_NUM_SCANS  # window length used by estimate_sequence (target + supports)
    max_offset: int = 0              # estimate_sequence: support scans at most this many frames from
                                     # the target (0: any); the windows at a sequence's ends, shifted
                                     # inwards, are then shorter (issue 47)
    time_weight_power: float = 2.0   # w(t) = 1 / |t|^power  (paper: 1/t^2)
    lambda_d: float = 1.0
    # regularisers
    cluster_loss: bool = True        # ablation switch for the cluster-consistency loss
    lambda_c: float = 0.6
    flow_norm_loss: bool = True      # ablation switch for the flow-magnitude regulariser
    lambda_g_start: float = 0.1
    lambda_g_end: float = 0.01
    lambda_g_decay_iters: int = 100
    reg_scale: str = "support"       # "support" (S), "paper" (2m - 1) or "weights" (the window's summed
                                     # time weights, 4 for the paper's centred 5 scans; issue 47)
    # clustering (DBSCAN on the target scan)
    dbscan_eps: float = 0.5
    dbscan_min_samples: int = 4
    # optimiser (Adam) and early stopping
    lr: float = 0.05
    max_iters: int = 500
    patience: int = 250
    min_delta: float = 0.01
    adam_betas: tuple[float, float] = (0.9, 0.999)
    adam_eps: float = 1e-8
    # safety
    max_dt_cells: int = DEFAULT_MAX_CELLS  # memory cap for one distance transform (samples)

    # ---- faithfulness readings (issue 20; bench/compare.py --ablations port) -------------
    # Where the paper's text leaves room, a peer's public port reads it differently; these
    # switch each reading on (defaults = this project's reading, measured in bench/RESULTS.md).
    lr_milestones: tuple[int, ...] = ()  # iterations where lr is multiplied by lr_gamma (port: (10, 20))
    lr_gamma: float = 0.5            # (MultiStepLR stepped once per iteration)
    truncation_mode: str = "zero"    # DT samples >= truncation count as 0 ("zero") or as the
                                     # truncation itself ("clamp", port); zero gradient in both
    cluster_loss_mean: str = "all"   # cluster term averaged over all points ("all", the paper's
                                     # 1/N) or over the clustered (non-noise) points ("clustered")

    # ---- motion evidence (issue 29; estimator/evidence.py) ---------------------------------
    # After the optimisation, each DBSCAN cluster (unclustered points: per flow-grid cell) is
    # tested: does its flow explain the support scans better than zero flow, by more than
    # max(evidence_margin, evidence_ratio * zero-flow residual)? "off": not computed (the
    # paper's output); "score": result.evidence / result.explained filled, flow untouched;
    # "zero": also the flow of unexplained groups set to 0 (floxels run's default).
    evidence: str = "off"
    evidence_margin: float = 0.02    # metres of mean DT residual the flow must remove (lidar range
                                     # noise: a smaller gain is no evidence)
    evidence_ratio: float = 0.05     # and this share of the zero-flow residual (far, sparse groups)
    # With the sights (range_mask / visibility, issue 47; evidence.seen_evidence): each group judged
    # on the support scans that saw its points (their weighted mean residual, not a share of all
    # scans' weights), and groups no support scan saw keep their flow (no evidence either way)
    evidence_seen_mean: bool = False
    evidence_keep_unseen: bool = False
    # with the evidence test on, a group whose final flow is more vertical than horizontal keeps none:
    # no road user moves mostly up or down, a lidar's rings sliding along a facade as the sensor
    # moves do (estimator/evidence_checks.py, judged after the refinement: estimator/post.py)
    evidence_upright: bool = False
    # the groups that pass must also explain the window's farther scans (all but the nearest in
    # time) better than zero flow, by evidence_ratio of their residual: the nearest scans carry most
    # of the weight, and a lone far point fits their sampling (estimator/evidence_checks.py; "off",
    # "unclustered": DBSCAN noise's groups only, "all")
    evidence_far: str = "off"

    # ---- beyond the paper (issue 33; the "accurate" preset, estimator/refine.py) ----------
    # Off in the paper's configuration (results bit for bit as before).
    velocity_search: bool = False    # start the grid from each cluster's searched constant velocity
    # The evidence test (and the velocity search) count a support scan only for points whose own
    # position it could see (estimator/sight.py; both need sensor_origins):
    range_mask: bool = False         # ... inside the horizontal range band it observed (its crop)
    visibility: bool = False         # ... where its range image has a return at or beyond the point
                                     # (its ground returns count where given: ground_points=)
    rigid_refine: bool = False       # refine each moving cluster as a rigid body after the optimisation
    refine_max_supports: int = 0     # ... only in windows of at most this many support scans (0: all).
                                     # Speed shrinkage, which the refinement corrects, is a few-scan
                                     # failure (2 scans: AV2 cars at 0.57 of their speed; 5-11 scans:
                                     # 0.99 on the simulator); with 9-11 scans it cost 10x the time
                                     # and raised urban dynamic EPE (bench/RESULTS.md, accurate preset)
    refine_sided: bool = False       # ... and the longer windows too, where a cluster keeps its rigid
                                     # motion only if it explains the window's past scans and its
                                     # future scans each no worse than its flow (refine.rigid_refine:
                                     # turning cars; no effect with refine_max_supports=0)
    refine_search: bool = False      # ... started also from each moving cluster's searched velocity
                                     # (the velocity search over the refined clusters), keeping the
                                     # lower-cost motion: the loop is local (refine.rigid_refine; in
                                     # a one-sided window, with refine_sided, only a motion that explains
                                     # the near and the far scans each no worse: issue 47)
    refine_level: bool = False       # ... also solved with no vertical velocity, the lower cost kept
                                     # (refine.rigid_refine; issue 47)
    refine_spread: float = 0.0       # m: the accepted rigid motions offered to the points within this
                                     # distance of their clusters (the rest of a far or sparse object:
                                     # estimator/spread.py; 0: off; issue 47)

    @classmethod
    def preset(cls, name: str, **changes) -> "FloxelsConfig":
        """A named configuration: ``"paper"`` (the paper's settings, the defaults) or
        ``"accurate"`` (beyond the paper, docs/accurate.md); ``changes`` override
        fields of it."""
        if name not in PRESETS:
            raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
        return cls(**{**PRESETS[name], **changes})

    def __post_init__(self) -> None:
        # types first, generically from the field annotations (fields added later are covered)
        check_field_types(self)

        def pos(name: str) -> None:
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"FloxelsConfig.{name} must be a positive finite number, got {v!r}")

        def nonneg(name: str) -> None:
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"FloxelsConfig.{name} must be a non-negative finite number, got {v!r}")

        for n in ("voxel_size", "dt_cell", "truncation", "lr", "dbscan_eps", "adam_eps"):
            pos(n)
        for n in ("dt_padding", "time_weight_power", "lambda_d", "lambda_c", "lambda_g_start",
                  "lambda_g_end", "min_delta"):
            nonneg(n)
        for n in ("max_iters", "patience", "dbscan_min_samples", "max_dt_cells", "num_scans"):
            v = getattr(self, n)
            if v < 1:
                raise ValueError(f"FloxelsConfig.{n} must be a positive integer, got {v!r}")
        if self.max_offset < 0:
            raise ValueError(f"FloxelsConfig.max_offset must be an integer >= 0 (0: any offset), got {self.max_offset!r}")
        if not (math.isfinite(self.refine_spread) and 0 <= self.refine_spread <= 10):
            raise ValueError(f"FloxelsConfig.refine_spread must lie in [0, 10] m (0: off), got {self.refine_spread!r}")
        if self.refine_max_supports < 0:
            raise ValueError(f"FloxelsConfig.refine_max_supports must be an integer >= 0 (0: every window), "
                             f"got {self.refine_max_supports!r}")
        if self.lambda_g_decay_iters < 0:
            raise ValueError(f"FloxelsConfig.lambda_g_decay_iters must be an integer >= 0, "
                             f"got {self.lambda_g_decay_iters!r}")
        if not 2 <= self.num_scans <= 13:
            raise ValueError(f"FloxelsConfig.num_scans must be in [2, 13], got {self.num_scans}")
        if self.reg_scale not in ("support", "paper", "weights"):
            raise ValueError(f"FloxelsConfig.reg_scale must be 'support', 'paper' or 'weights', got {self.reg_scale!r}")
        self._check_readings()
        b1, b2 = self.adam_betas
        if not (0 <= b1 < 1 and 0 <= b2 < 1):
            raise ValueError(f"FloxelsConfig.adam_betas must lie in [0, 1), got {self.adam_betas}")
        if self.dt_cell > self.voxel_size * 4:
            raise ValueError(f"FloxelsConfig.dt_cell ({self.dt_cell}) should be much finer than "
                             f"voxel_size ({self.voxel_size})")

    @classmethod
    def from_strings(cls, options: dict[str, str], base: "FloxelsConfig | None" = None) -> "FloxelsConfig":
        """A config from ``{field: text}`` (e.g. the CLI's ``--option KEY=VALUE``), each text
        parsed for its field's type by :func:`parse_option_value`; ``base`` supplies the
        other fields (default: the paper's defaults). Unknown fields or unparsable values
        raise ``ValueError`` naming them."""
        values = {k: _parse_field(cls, k, v) for k, v in options.items()}
        return dataclasses.replace(base, **values) if base is not None else cls(**values)

    def _check_readings(self) -> None:
        ms = self.lr_milestones
        if (not isinstance(ms, (tuple, list)) or len(ms) > 4
                or not all(isinstance(m, int) and not isinstance(m, bool) and m >= 1 for m in ms)
                or list(ms) != sorted(ms)):
            raise ValueError(f"FloxelsConfig.lr_milestones must be up to 4 increasing integers >= 1, got {ms!r}")
        g = self.lr_gamma
        if not (isinstance(g, (int, float)) and not isinstance(g, bool) and math.isfinite(g) and g > 0):
            raise ValueError(f"FloxelsConfig.lr_gamma must be a positive finite number, got {g!r}")
        if self.truncation_mode not in ("zero", "clamp"):
            raise ValueError(f"FloxelsConfig.truncation_mode must be 'zero' or 'clamp', got {self.truncation_mode!r}")
        if self.evidence not in EVIDENCE_MODES:
            raise ValueError(f"FloxelsConfig.evidence must be 'off', 'score' or 'zero', got {self.evidence!r}")
        if self.evidence_far not in FAR_MODES:
            raise ValueError(f"FloxelsConfig.evidence_far must be one of {', '.join(map(repr, FAR_MODES))}, "
                             f"got {self.evidence_far!r}")
        em, er = self.evidence_margin, self.evidence_ratio
        if not (math.isfinite(em) and em >= 0):
            raise ValueError(f"FloxelsConfig.evidence_margin must be a non-negative finite number (m), got {em!r}")
        if not (math.isfinite(er) and 0 <= er < 1):
            raise ValueError(f"FloxelsConfig.evidence_ratio must lie in [0, 1), got {er!r}")
        if self.cluster_loss_mean not in ("all", "clustered"):
            raise ValueError(f"FloxelsConfig.cluster_loss_mean must be 'all' or 'clustered', "
                             f"got {self.cluster_loss_mean!r}")

    def lr_at(self, it: int) -> float:
        """Learning rate of the Adam step of iteration ``it`` (0-based)."""
        return self.lr * self.lr_gamma ** sum(1 for m in self.lr_milestones if m <= it)

    def replace(self, **changes) -> "FloxelsConfig":
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def lambda_g(self, it: int) -> float:
        """Flow-norm weight at iteration ``it`` (linear decay, then constant)."""
        if self.lambda_g_decay_iters == 0 or it >= self.lambda_g_decay_iters:
            return self.lambda_g_end
        a = it / self.lambda_g_decay_iters
        return self.lambda_g_start + a * (self.lambda_g_end - self.lambda_g_start)

    def time_weight(self, t: float) -> float:
        """w(t) = 1 / |t|^power for a time offset ``t`` in frame periods (any real t != 0:
        unequally spaced scans give non-integer offsets)."""
        return 1.0 / abs(t) ** self.time_weight_power

    def regulariser_scale(self, num_support: int, offsets=None) -> float:
        """The regularisers' factor for a window of ``num_support`` support scans at time
        offsets ``offsets`` (frame periods; read by ``reg_scale="weights"`` only)."""
        if self.reg_scale == "support":
            return float(num_support)
        if self.reg_scale == "weights":
            # the paper scales the regularisers "similarly" to the data term, which sums the time
            # weights: with 1/t^2 the 11-scan window's data term is 1.17x the 5-scan one's, not
            # 2.5x, and a count over-regularised it (a parking lot: no flow at all, bench/RESULTS.md
            # issue 47). Normalised so that the paper's centred 5-scan window gets its 4.
            if offsets is None:
                raise ValueError("reg_scale='weights' needs the window's time offsets")
            ref = sum(self.time_weight(t) for t in (-2, -1, 1, 2))
            return 4.0 * sum(self.time_weight(t) for t in offsets) / ref
        # paper: (2m - 1) with 2m support scans
        return float(max(num_support - 1, 1))


def parse_option_value(field: str, text: str, cls=FloxelsConfig):
    """The value of config field ``field`` written as ``text`` (the CLI's ``--option
    field=text``), parsed for the field's annotated type: bools accept true/false, yes/no,
    on/off, 1/0; tuples ``a,b`` or ``[a,b]``; numbers as Python writes them. ``ValueError``
    naming the field otherwise (an unknown field lists the known ones). ``cls``: another
    dataclass config (e.g. a baseline's)."""
    return _parse_field(cls, field, text)
