"""Every weight of the loss and every ablation switch, set through the estimator, changes the
result by what the loss's formula says (issue 46): known answers on the hand-made scenes of
test_paper_settings.py (points on the 0.1 m DT lattice at known distances; a wall moving 0.5 m a
frame, whose first Adam step is the same whatever the regularisers, since they have no gradient
at the zero start).

Loss at iteration ``it`` (S = 4 support scans here)::

    lambda_d * sum_t |t|^-power * mean_i DT_t(p_i + t f_i) + S * (lambda_c * l_C + lambda_g(it) * mean_i ||f_i||)
"""

import warnings

import numpy as np
import pytest

from floxels_ext import Floxels, FloxelsConfig
from test_paper_settings import _moving_wall, _regularisers, _truncation_scene

S = 4  # support scans of the 5-scan scenes


def _first_loss(cfg):
    return Floxels(cfg.replace(max_iters=1), "cpu").fit(_truncation_scene(), target=2).losses[0]


# zero flow on the truncation scene: mean DT over the 9 target points = (4.0 + 4.9) / 9 per
# support scan (the 5.1 and 10 m samples are beyond the 5 m truncation: 0)
MEAN_DT = (4.0 + 4.9) / 9


@pytest.mark.parametrize("lambda_d", [2.0, 0.5])
def test_lambda_d_scales_the_distance_term(lambda_d):
    # supports at t = -2, -1, 1, 2 weigh 1/4 + 1 + 1 + 1/4 = 2.5
    assert _first_loss(FloxelsConfig(lambda_d=lambda_d)) == pytest.approx(lambda_d * 2.5 * MEAN_DT, rel=1e-5)


@pytest.mark.parametrize("power, weights", [(1.0, 0.5 + 1 + 1 + 0.5), (0.0, 4.0), (3.0, 0.125 + 1 + 1 + 0.125)])
def test_time_weight_power_weighs_each_support_scan(power, weights):
    assert _first_loss(FloxelsConfig(time_weight_power=power)) == pytest.approx(weights * MEAN_DT, rel=1e-5)


# Adam's first step is lr * g / (|g| + eps): lr * sign(g) but for components whose gradient is
# near eps (zero up to rounding); a tiny eps makes it lr * sign(g) for every component, so the
# first step is the same whatever scales the gradient (lambda_d)
EPS = 1e-30


@pytest.fixture(scope="module")
def wall():
    return _moving_wall()


@pytest.fixture(scope="module")
def base(wall):
    """Two iterations with the paper's settings: the first step (the same in every case below;
    it is the result here, but need not be elsewhere: the result is the lowest loss's flow) and
    the loss after it."""
    scans, _ = wall
    res = Floxels(FloxelsConfig(max_iters=2, adam_eps=EPS), "cpu").fit(scans, target=2)
    c, g, _ = _regularisers(res.flow, res.labels.numpy())
    assert res.best_iter == 1 and c > 1e-3 and g > 1e-3  # both regularisers are live after the first step
    return res, c / len(res.flow), g


def _two_steps(wall, **change):
    scans, _ = wall
    return Floxels(FloxelsConfig(max_iters=2, adam_eps=EPS, **change), "cpu").fit(scans, target=2)


# After the first step the loss is D + S * (lambda_c * lC + lambda_g(1) * g), with lambda_g(1) =
# 0.1 + (0.01 - 0.1) / 100 = 0.0991. Each case: the change and the loss it gives, from the
# paper's run's D (base loss minus its regularisers), lC and g.
CASES = {
    "lambda_d=0.5": (dict(lambda_d=0.5), lambda d, lc, g: 0.5 * d + S * (0.6 * lc + 0.0991 * g)),
    "cluster_loss off": (dict(cluster_loss=False), lambda d, lc, g: d + S * 0.0991 * g),
    "flow_norm_loss off": (dict(flow_norm_loss=False), lambda d, lc, g: d + S * 0.6 * lc),
    "both off": (dict(cluster_loss=False, flow_norm_loss=False), lambda d, lc, g: d),
    "lambda_c=0.3": (dict(lambda_c=0.3), lambda d, lc, g: d + S * (0.3 * lc + 0.0991 * g)),
    "lambda_c=0": (dict(lambda_c=0.0), lambda d, lc, g: d + S * 0.0991 * g),
    # lambda_g(1) = 0.2 + (0.01 - 0.2) / 100
    "lambda_g_start=0.2": (dict(lambda_g_start=0.2), lambda d, lc, g: d + S * (0.6 * lc + 0.1981 * g)),
    # lambda_g(1) = 0.1 + (0.05 - 0.1) / 100
    "lambda_g_end=0.05": (dict(lambda_g_end=0.05), lambda d, lc, g: d + S * (0.6 * lc + 0.0995 * g)),
    # lambda_g(1) = 0.1 + (0.01 - 0.1) / 10
    "lambda_g_decay_iters=10": (dict(lambda_g_decay_iters=10), lambda d, lc, g: d + S * (0.6 * lc + 0.091 * g)),
    "lambda_g_decay_iters=0": (dict(lambda_g_decay_iters=0), lambda d, lc, g: d + S * (0.6 * lc + 0.01 * g)),
    "reg_scale=paper": (dict(reg_scale="paper"), lambda d, lc, g: d + (S - 1) * (0.6 * lc + 0.0991 * g)),
}


@pytest.mark.parametrize("case", list(CASES))
def test_each_weight_and_switch_changes_the_loss_as_its_formula_says(wall, base, case):
    res0, lc, g = base
    d = res0.losses[1] - S * (0.6 * lc + 0.0991 * g)  # the distance term after the first step
    change, expected = CASES[case]
    res = _two_steps(wall, **change)
    assert res.losses[0] == pytest.approx(change.get("lambda_d", 1.0) * res0.losses[0], rel=1e-6)
    assert res.losses[1] == pytest.approx(expected(d, lc, g), rel=1e-4), (res.losses[1], res0.losses[1])
    if not change.get("cluster_loss", True):
        assert res.labels is None  # no DBSCAN without the cluster term


def test_switches_change_the_whole_optimisation(wall):
    """Beyond the first steps: the wall's recovered motion (0.5 m a frame) with each ablation.
    Without the flow-norm pull towards zero the wall gets all of its motion; the paper's
    settings stop within 1 cm of it; with lambda_d = 0 nothing moves at all."""
    scans, nw = wall
    full = Floxels(FloxelsConfig(), "cpu").fit(scans, target=2)
    free = Floxels(FloxelsConfig(flow_norm_loss=False), "cpu").fit(scans, target=2)
    np.testing.assert_allclose(full.flow[:nw].mean(0), [0.5, 0, 0], atol=0.01)
    np.testing.assert_allclose(free.flow[:nw].mean(0), [0.5, 0, 0], atol=0.01)
    assert not np.array_equal(full.flow, free.flow)
    none = Floxels(FloxelsConfig(lambda_d=0.0, max_iters=20), "cpu").fit(scans, target=2)
    assert np.all(none.flow == 0) and none.losses == [0.0] * 20


@pytest.mark.parametrize("preset", ["paper", "accurate"])
def test_lambda_d_zero_with_the_evidence_and_the_refinement(wall, preset):
    """lambda_d = 0 (the scans out of the loss) with the evidence test and the refinement: no
    division by the zero sum of the weights; the flow stays zero and nothing is explained."""
    scans, _ = wall
    cfg = FloxelsConfig.preset(preset, lambda_d=0.0, max_iters=10, evidence="score", velocity_search=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the accurate preset without sensor_origins
        res = Floxels(cfg, "cpu").fit(scans, target=2)
    assert np.all(res.flow == 0) and not res.explained.any()
