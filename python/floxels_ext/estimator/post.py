"""After the optimiser, per solved problem (rows in the solver's order): what each support scan
saw of the target (estimator/sight.py), the motion evidence test (estimator/evidence.py) and the
rigid refinement with its spreading to the refined objects' other points (estimator/refine.py),
in the order the ``accurate`` preset applies them. Nothing here runs with the paper's settings.
A group's problems run together (:func:`after_optimisation_all`): their few host reads are merged,
one synchronisation per round for all of them (estimator/host_reads.py)."""

from __future__ import annotations

from dataclasses import replace

import torch

from floxels_ext.estimator.config import FloxelsConfig
from floxels_ext.estimator.evidence import MotionEvidence, run_evidence, sensor_velocity
from floxels_ext.estimator.evidence_checks import far_fails, upright_groups
from floxels_ext.estimator.host_reads import Steps, run_one, run_steps
from floxels_ext.estimator.refine import rigid_refine_steps, supports_of
from floxels_ext.estimator.sight import observed_bits
from floxels_ext.estimator.spread import spread_rigid_steps
from floxels_ext.estimator.unseen import hidden_keeps
from floxels_ext.ops.solver import SolverProblem

__all__ = ["after_optimisation", "after_optimisation_all", "after_optimisation_steps", "problem_evidence",
           "problem_observed"]


def after_optimisation(cfg: FloxelsConfig, problem: SolverProblem,
                       flow: torch.Tensor) -> tuple[torch.Tensor, MotionEvidence | None]:
    """(the flow after the evidence test and the rigid refinement, the evidence or None) of one
    solved problem's optimiser flow ``flow`` (solver order)."""
    return run_one(after_optimisation_steps(cfg, problem, flow))


def after_optimisation_all(cfg: FloxelsConfig, problems: list[SolverProblem],
                           flows: list[torch.Tensor]) -> list[tuple[torch.Tensor, MotionEvidence | None]]:
    """:func:`after_optimisation` of several problems, their host reads merged (one per round for
    all of them: estimator/host_reads.py); each result the same bits as alone."""
    if not _anything_after(cfg):
        return [(flow, None) for flow in flows]
    return run_steps([after_optimisation_steps(cfg, p, f) for p, f in zip(problems, flows)])


def _anything_after(cfg: FloxelsConfig) -> bool:
    """Whether anything runs after the optimiser (not with the paper's settings)."""
    return cfg.evidence != "off" or cfg.rigid_refine


def after_optimisation_steps(cfg: FloxelsConfig, problem: SolverProblem, flow: torch.Tensor) -> Steps:
    """:func:`after_optimisation` as steps of estimator/host_reads.py (the refinement's and the
    spreading's host reads yielded)."""
    p = problem
    short = cfg.refine_max_supports <= 0 or len(p.dts) <= cfg.refine_max_supports
    refine = cfg.rigid_refine and (short or cfg.refine_sided)
    # the sights' bits once for the evidence test and the refinement's spreading
    observed = occluded = None
    if p.sights is not None and cfg.evidence != "off" and cfg.evidence_keep_unseen:
        observed, occluded = observed_bits(p.points, p.sights, occluded=True)
    elif cfg.evidence != "off" or (refine and cfg.refine_spread > 0):
        observed = problem_observed(p)
    ev = None
    raw = flow  # the optimiser's flow: what evidence="score" keeps where the final verdict rejects
    if cfg.evidence != "off":
        ev = problem_evidence(cfg, p, flow, observed, occluded)
        # both modes run the same steps on the zeroed flow: "score" differs from "zero" only in
        # the rows of the groups the final verdict rejects (below), so a user filtering a
        # --raw-flow output with `explained` gets the default output's labels (issue 42; before,
        # "score" refined the unzeroed flow and kept hidden groups the refinement did not confirm)
        flow = ev.apply(flow)
    # after the evidence test: the refinement must not revive a group the scans gave no
    # evidence of motion (static structure seen in a band that moves with the sensor is
    # fitted *better* by a rigid motion: simulated highway, static EPE 0.52 -> 0.99 when
    # the test judged the refined flow); the verdict stays the optimiser flow's
    motions = None
    if refine:
        supports = supports_of(p.dts, p.origins, p.time_offsets, p.weights, cfg.dt_cell)
        flow, motions = yield from rigid_refine_steps(p.points, flow, p.labels, supports,
                                                      num_clusters=p.num_clusters, sided=not short,
                                                      search=cfg.refine_search, motions=True, level=cfg.refine_level)
    explained = None if ev is None else ev.explained
    if ev is not None and ev.hidden is not None:
        # a group kept only because no scan saw it (something in front of it each time) keeps its
        # flow where a rigid motion explains the scans (all of them) clearly better than zero flow
        # (a car approaching from behind, at a sequence's first frame); static structure hidden
        # behind passing traffic is seen around the hidden part: zero flow fits it, and it keeps
        # no arbitrary flow. The flow kept must itself fit, and must not move the group onto
        # the target's static structure (estimator/unseen.py: a parked car in a row of them)
        keep = torch.zeros_like(ev.hidden) if motions is None else hidden_keeps(
            p.points, flow, p.labels, ev.hidden, motions.fits, supports, p.num_clusters)
        dropped = ev.hidden & ~keep
        flow = torch.where(dropped[:, None], torch.zeros_like(flow), flow)
        explained = explained & ~dropped
    if motions is not None and cfg.refine_spread > 0:
        flow = yield from spread_rigid_steps(p.points, flow, p.labels, supports, motions, cfg.refine_spread,
                                             observed=observed)
    if ev is not None and cfg.evidence_upright:
        # no road user moves mostly up or down: a group whose final flow does (the optimiser's, or
        # a refined or spread motion) keeps none (estimator/evidence_checks.py). After the
        # refinement, which solves without vertical velocity too (refine_level): at a sequence's
        # first frame the optimiser left running pedestrians a mostly vertical flow that the
        # refinement corrected (tuning seed 1, urban: 45 points at 1.1 m/frame)
        up = upright_groups(flow, p.labels, p.num_clusters)
        flow = torch.where(up[:, None], torch.zeros_like(flow), flow)
        explained = explained & ~up
    if ev is not None:
        # the final verdict: a rejected group that took a spread motion (tested against zero flow
        # there) is explained; every rejected row's flow is 0 here, every moving row explained
        explained = explained | (flow != 0).any(dim=1)
        ev = replace(ev, explained=explained)
        if cfg.evidence == "score":
            flow = torch.where(explained[:, None], flow, raw)
    return flow, ev


def problem_evidence(cfg: FloxelsConfig, problem: SolverProblem, flow: torch.Tensor,
                     observed: torch.Tensor | None = None, occluded: torch.Tensor | None = None) -> MotionEvidence:
    """:func:`~floxels_ext.estimator.evidence.motion_evidence` of one solved problem (rows in
    the solver's order: sorted by (cluster, flow-grid cell), so the groups, clusters and the
    unclustered points' cells, are runs), on the distance transforms its loss used: one
    ``floxels::dt_evidence`` call (:func:`~floxels_ext.estimator.evidence.run_evidence`).
    ``observed``: the problem's :func:`problem_observed` bits if already computed; ``occluded``:
    the sights' bits of the scans that show something in front of each point (``keep_unseen``)."""
    if observed is None:
        observed = problem_observed(problem)
    # cells: the compact index of each point's lower flow-grid corner (one per cell)
    ev = run_evidence(problem.points, flow, problem.labels, problem.corners.corner_idx[:, 0], problem.dts,
                      problem.origins, problem.time_offsets, problem.weights, dt_cell=cfg.dt_cell,
                      truncation=cfg.truncation, margin=cfg.evidence_margin, ratio=cfg.evidence_ratio,
                      observed=observed, seen_mean=cfg.evidence_seen_mean, keep_unseen=cfg.evidence_keep_unseen,
                      occluded=occluded, sights=problem.sights,
                      sensor_velocity=None if problem.sights is None or not cfg.evidence_seen_mean
                      else sensor_velocity([None if s is None else s.sensor for s in problem.sights],
                                           problem.time_offsets))
    if cfg.evidence_far != "off":
        # the groups that passed explain the farther scans too (estimator/evidence_checks.py)
        fails = far_fails(problem.points, flow, problem.labels, problem.corners.corner_idx[:, 0], problem.dts,
                          problem.origins, problem.time_offsets, problem.weights, dt_cell=cfg.dt_cell,
                          truncation=cfg.truncation, ratio=cfg.evidence_ratio, observed=observed,
                          unclustered=cfg.evidence_far == "unclustered")
        if fails is not None:
            ev = replace(ev, explained=ev.explained & ~fails,
                         hidden=None if ev.hidden is None else ev.hidden & ~fails)
    return ev


def problem_observed(problem: SolverProblem) -> torch.Tensor | None:
    """(n,) int32 observed bits of a problem's points (estimator/sight.py), or None."""
    return None if problem.sights is None else observed_bits(problem.points, problem.sights)
