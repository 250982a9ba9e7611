"""Property-style fuzzing of the ops (fixed seed, plain torch random): valid calls with one
argument broken at a time (wrong shape, dtype, device, length; NaN/inf/huge values; empty or
mismatched tensors; absurd scalars), through the public wrappers and the raw
``torch.ops.floxels`` ops. Every call must either raise a clear exception (RuntimeError /
ValueError / TypeError naming the problem) or return a result that keeps the op's documented
properties (docs/ops.md, "Non-finite and extreme input"). Never a crash."""

from __future__ import annotations

import math
import random

import torch

import floxels_ext.ops as W
from floxels_ext.reference import ops as ref

OPS = torch.ops.floxels
ALLOWED = (RuntimeError, ValueError, TypeError, NotImplementedError)
SHAPE = [3, 4, 5]
ORIGIN = [-0.3, 0.1, -0.7]


def _pts(n, rnd, dtype=torch.float32):
    return (torch.rand(n, 3, dtype=torch.float64) * 3 - 1).to(dtype)


def _bad_tensor(t: torch.Tensor, rnd: random.Random):
    """One broken variant of tensor t (or a non-tensor)."""
    kind = rnd.randrange(11)
    if kind == 0:
        return t[:, :2] if t.dim() == 2 else t[..., :1]           # wrong trailing size
    if kind == 1:
        return t.reshape(-1)                                        # wrong number of dims
    if kind == 2:
        return t.to(torch.int64) if t.is_floating_point() else t.float()  # wrong dtype
    if kind == 3:
        return t.half() if t.is_floating_point() else t.to(torch.int32)
    if kind == 4:
        return t[:0]                                                # empty
    if kind == 5:
        return t[1:] if t.shape[0] > 1 else torch.cat([t, t])       # mismatched length
    if kind == 6:
        return torch.empty_like(t, device="meta")                  # another device
    if kind == 7:
        return t.tolist()                                           # not a tensor
    if kind == 8 and t.is_floating_point() and t.numel():
        u = t.clone()
        flat = u.view(-1)
        for _ in range(rnd.randrange(1, 4)):
            flat[rnd.randrange(flat.numel())] = rnd.choice([math.nan, math.inf, -math.inf, 1e30, -1e30, 3e38])
        return u
    if kind == 9 and t.dim() >= 2:
        return t.transpose(0, 1).contiguous().transpose(0, 1)       # non-contiguous, same values
    return t


def _bad_scalar(name, v, rnd):
    if name == "origin":
        return rnd.choice([[0.0, 0.0], [math.nan, 0.0, 0.0], [0.0, math.inf, 0.0], [1e300, 0.0, 0.0], "abc"])
    if name == "spacing":
        return rnd.choice([0.0, -1.0, math.nan, math.inf, 1e-40, 1e40, "x"])
    if name == "grid_shape":
        return rnd.choice([[0, 4, 5], [3, -1, 5], [3, 4], [2**31] * 3, [1, 1, 2**62]])
    if name in ("num_clusters", "num_params", "min_samples", "tile"):
        return rnd.choice([-1, 0, -(2**40)])
    if name in ("eps", "truncation"):
        return rnd.choice([0.0, -1.0, math.nan, math.inf])
    if name in ("time_offsets", "weights"):
        return rnd.choice([[], [math.nan], [1.0, 2.0], [math.inf]])
    if name == "origins":
        return rnd.choice([[0.0] * 2, [math.nan, 0.0, 0.0]])
    return v


def _finite_rows(p):
    return torch.isfinite(p).all(dim=1)


# Each spec: argument names (the call's order), a maker of valid arguments, and the property
# that any accepted call must keep.

def _gather_ok(a, out):
    assert out.shape == (a["points"].shape[0], a["grid"].shape[0])
    if torch.isfinite(a["grid"]).all():
        assert torch.equal(torch.isnan(out).all(dim=1) if out.shape[1] else ~_finite_rows(a["points"]),
                           ~_finite_rows(a["points"]))
        assert torch.isfinite(out[_finite_rows(a["points"])]).all()


def _scatter_ok(a, out):
    assert out.shape == (a["values"].shape[1], *a["grid_shape"])
    if torch.isfinite(a["values"][_finite_rows(a["points"])]).all():
        assert torch.isfinite(out).all()


def _occ_ok(a, out):
    assert out.dtype == torch.bool and list(out.shape) == list(a["grid_shape"])
    assert torch.equal(out, ref.points_to_occupancy(a["points"], a["origin"], a["spacing"], a["grid_shape"]))


def _dt_ok(a, out):
    if not all(bool((d.abs() < 1e20).all()) for d in a["dts"]):
        return  # non-finite or absurd distance-transform values propagate: nothing to promise
    loss = out[0] if isinstance(out, tuple) else out
    bad = not bool((_finite_rows(a["points"]) & _finite_rows(a["flow"])).all())
    assert math.isnan(loss.item()) == bad
    if isinstance(out, tuple):
        assert torch.isfinite(out[1]).all()


def _dbscan_ok(a, out):
    assert out.shape == (a["points"].shape[0],) and bool(((out >= -1) & (out < max(1, out.numel()))).all())


def _shape_ok(shape_fn):
    def check(a, out):
        assert tuple(out.shape) == tuple(shape_fn(a))
    return check


def _setup_ok(a, out):
    order = out.order if isinstance(out, W.ProblemSetup) else out[0]
    assert torch.equal(order.sort().values, torch.arange(a["points"].shape[0]))


def _dts(rnd):
    return [torch.rand(3, 4, 5) * 3, torch.rand(2, 3, 3) * 3]


SPECS = {
    "trilinear_gather": (["grid", "points", "origin", "spacing"],
                         lambda r: dict(grid=torch.randn(2, *SHAPE), points=_pts(20, r), origin=ORIGIN, spacing=0.5),
                         _gather_ok),
    "trilinear_scatter": (["values", "points", "origin", "spacing", "grid_shape"],
                          lambda r: dict(values=torch.randn(20, 2), points=_pts(20, r), origin=ORIGIN, spacing=0.5,
                                         grid_shape=SHAPE),
                          _scatter_ok),
    "points_to_occupancy": (["points", "origin", "spacing", "grid_shape"],
                            lambda r: dict(points=_pts(20, r), origin=ORIGIN, spacing=0.5, grid_shape=SHAPE),
                            _occ_ok),
    "dt_loss": (["points", "flow", "dts", "origins", "spacing", "time_offsets", "weights", "truncation"],
                lambda r: dict(points=_pts(20, r), flow=torch.randn(20, 3) * 0.2, dts=_dts(r),
                               origins=ORIGIN + [0.0, 0.0, 0.0], spacing=0.5, time_offsets=[1.0, -1.0],
                               weights=[1.0, 0.5], truncation=2.0),
                _dt_ok),
    "dt_loss_fwd_bwd": (["points", "flow", "dts", "origins", "spacing", "time_offsets", "weights", "truncation"],
                        lambda r: dict(points=_pts(20, r), flow=torch.randn(20, 3) * 0.2, dts=_dts(r),
                                       origins=ORIGIN + [0.0, 0.0, 0.0], spacing=0.5, time_offsets=[1.0, -1.0],
                                       weights=[1.0, 0.5], truncation=2.0),
                        _dt_ok),
    "dbscan": (["points", "eps", "min_samples"], lambda r: dict(points=_pts(30, r), eps=0.5, min_samples=3),
               _dbscan_ok),
    "cluster_mean": (["values", "labels", "num_clusters"],
                     lambda r: dict(values=torch.randn(20, 3), labels=torch.randint(-1, 4, (20,)), num_clusters=4),
                     _shape_ok(lambda a: (a["num_clusters"], a["values"].shape[1]))),
    "cluster_consistency_loss": (["flow", "labels", "num_clusters"],
                                 lambda r: dict(flow=torch.randn(20, 3), labels=torch.randint(-1, 4, (20,)),
                                                num_clusters=4),
                                 _shape_ok(lambda a: ())),
    "corner_gather": (["params", "corner_idx", "corner_w"],
                      lambda r: dict(params=torch.randn(10, 3), corner_idx=torch.randint(0, 10, (20, 8),
                                                                                          dtype=torch.int32),
                                     corner_w=torch.rand(20, 8)),
                      _shape_ok(lambda a: (a["corner_idx"].shape[0], a["params"].shape[1]))),
    "corner_scatter": (["values", "corner_idx", "corner_w", "num_params"],
                       lambda r: dict(values=torch.randn(20, 3), corner_idx=torch.randint(0, 10, (20, 8),
                                                                                           dtype=torch.int32),
                                      corner_w=torch.rand(20, 8), num_params=10),
                       _shape_ok(lambda a: (a["num_params"], a["values"].shape[1]))),
    "edt": (["occupancy", "spacing"], lambda r: dict(occupancy=torch.rand(*SHAPE) < 0.2, spacing=0.5),
            _shape_ok(lambda a: a["occupancy"].shape)),
    "problem_setup": (["points", "labels", "origin", "spacing", "grid_shape", "tile"],
                      lambda r: dict(points=_pts(20, r), labels=torch.randint(-1, 3, (20,)), origin=ORIGIN,
                                     spacing=0.5, grid_shape=SHAPE, tile=32),
                      _setup_ok),
}
WRAPPED = {"trilinear_gather", "trilinear_scatter", "points_to_occupancy", "dt_loss", "dt_loss_fwd_bwd", "dbscan",
           "cluster_mean", "cluster_consistency_loss", "corner_gather", "corner_scatter", "edt", "problem_setup"}
# words a clear message may use instead of the argument's own name
ALIASES = {"dts": ["distance transform"], "occupancy": ["bool"], "points": ["finite", "NaN"],
           "flow": ["finite"], "grid_shape": ["grid", "elements"], "values": ["output grid", "elements"]}


def _call(op, names, a, raw):
    fn = getattr(OPS, op) if raw else getattr(W, op)
    return fn(*[a[n] for n in names])


def test_fuzz_ops_never_crash():
    rnd = random.Random(20261124)
    torch.manual_seed(20261124)
    outcomes = {"raised": 0, "ok": 0}
    for it in range(600):
        op = rnd.choice(sorted(SPECS))
        names, make, check = SPECS[op]
        a = make(rnd)
        broken = rnd.choice(names)
        v = a[broken]
        if isinstance(v, torch.Tensor):
            a[broken] = _bad_tensor(v, rnd)
        elif broken == "dts":
            a[broken] = [_bad_tensor(v[0], rnd), v[1]]
        else:
            a[broken] = _bad_scalar(broken, v, rnd)
        raw = op not in WRAPPED or rnd.random() < 0.5
        where = f"case {it}: {'torch.ops.floxels' if raw else 'floxels_ext.ops'}.{op} with {broken} broken"
        try:
            out = _call(op, names, a, raw)
        except ALLOWED as e:
            msg = str(e)
            words = [broken] + ALIASES.get(broken, []) + names + ["device", "meta"]
            assert any(w in msg for w in words), f"{where}: unclear message {msg!r}"
            outcomes["raised"] += 1
            continue
        flat = [x for v in a.values() for x in (v if isinstance(v, list) else [v])]
        if any(isinstance(x, torch.Tensor) and x.is_meta for x in flat):
            outcomes["ok"] += 1  # a meta tensor ran the fake kernel: shapes only
            continue
        try:
            check(a, out)
        except AssertionError as e:
            raise AssertionError(f"{where}: accepted but wrong: {e}") from e
        outcomes["ok"] += 1
    assert outcomes["raised"] > 100 and outcomes["ok"] > 100, outcomes
