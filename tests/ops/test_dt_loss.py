"""floxels::dt_loss (+ _backward, _fwd_bwd) against reference.dt_loss on fresh random inputs."""

from __future__ import annotations

import math

import pytest
import torch

import floxels_ext  # noqa: F401  (registers torch.ops.floxels.*)
from floxels_ext.reference import ops as ref
from floxels_ext.ops import dt_loss, dt_loss_fwd_bwd

ops = torch.ops.floxels
cuda = pytest.mark.cuda
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def make_case(K, n, dtype=torch.float64, seed=0, device="cpu"):
    """K distance transforms of different shapes/origins and n points, partly outside every grid.

    Half of the DTs are exact EDTs of random point clouds (reference.edt), half random
    positive fields; the truncation sits inside the value range so that it is crossed.
    """
    g = torch.Generator().manual_seed(seed)
    spacing = 0.25 + 0.75 * torch.rand((), generator=g).item()
    dts, origins = [], []
    for k in range(K):
        Z = int(torch.randint(1, 7, (), generator=g))
        Y = int(torch.randint(2, 9, (), generator=g))
        X = int(torch.randint(2, 11, (), generator=g))
        if k % 2 == 0:
            occ = torch.rand(Z, Y, X, generator=g) < 0.08
            occ.view(-1)[int(torch.randint(0, Z * Y * X, (), generator=g))] = True
            d = ref.edt(occ, spacing)
        else:
            d = 3.0 * torch.rand(Z, Y, X, generator=g) ** 2
        dts.append(d.to(device))
        origins += (torch.rand(3, generator=g) * 2 - 1).tolist()
    # points spread over a box larger than any grid: many clamp on some border
    lo, hi = -1.5, 1.5 + 10 * spacing
    points = lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64)
    flow = 0.7 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    t = (torch.rand(K, generator=g) * 2 - 1).tolist()
    t[0] = 1.0
    w = (0.2 + torch.rand(K, generator=g)).tolist()
    trunc = 1.2
    return dict(points=points.to(dtype).to(device), flow=flow.to(dtype).to(device), dts=dts, origins=origins,
                spacing=spacing, time_offsets=t, weights=w, truncation=trunc)


def args(c, flow=None):
    return (c["points"], c["flow"] if flow is None else flow, c["dts"], c["origins"], c["spacing"],
            c["time_offsets"], c["weights"], c["truncation"])


def ref_loss_grad(c):
    f = c["flow"].detach().clone().requires_grad_(True)
    loss = ref.dt_loss(*args(c, f))
    (g,) = torch.autograd.grad(loss, f, allow_unused=True)
    return loss.detach(), (torch.zeros_like(f) if g is None else g)


def tol(dtype):
    return dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("K", [1, 2, 3, 4])
@pytest.mark.parametrize("n", [0, 1, 17, 3000])
def test_value_matches_reference(dtype, K, n):
    c = make_case(K, n, dtype, seed=100 * K + n)
    got = ops.dt_loss(*args(c))
    want = ref.dt_loss(*args(c))
    assert got.dtype == dtype and got.shape == ()
    torch.testing.assert_close(got, want, **tol(dtype))


@pytest.mark.parametrize("K", [1, 2, 4])
def test_gradient_matches_reference_float64(K):
    c = make_case(K, 2000, torch.float64, seed=7 + K)
    want_loss, want_grad = ref_loss_grad(c)
    loss, grad = ops.dt_loss_fwd_bwd(*args(c))
    torch.testing.assert_close(loss, want_loss, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(grad, want_grad, rtol=1e-9, atol=1e-12)
    assert (grad != 0).any()


def test_gradient_matches_reference_float32():
    c = make_case(4, 2000, torch.float32, seed=3)
    _, want_grad = ref_loss_grad(c)
    _, grad = ops.dt_loss_fwd_bwd(*args(c))
    # float32 rounding of the sample coordinate may put a rare point into the neighbouring
    # cell (gradients are discontinuous across cells), so compare row-wise with a margin.
    bad = ~torch.isclose(grad, want_grad, rtol=1e-4, atol=1e-5).all(dim=1)
    assert int(bad.sum()) <= 2


def test_autograd_through_op_matches_backward():
    c = make_case(3, 500, torch.float64, seed=11)
    f = c["flow"].clone().requires_grad_(True)
    loss = ops.dt_loss(*args(c, f))
    loss.backward()
    _, want = ref_loss_grad(c)
    torch.testing.assert_close(f.grad, want, rtol=1e-9, atol=1e-12)
    # upstream gradient scaling
    f2 = c["flow"].clone().requires_grad_(True)
    (ops.dt_loss(*args(c, f2)) * -2.5).backward()
    torch.testing.assert_close(f2.grad, -2.5 * want, rtol=1e-9, atol=1e-12)


def _far_from_kinks(c, margin=1e-3):
    """Rows whose sample coordinates stay away from cell faces/borders and whose DT values
    stay away from the truncation, in every scan (finite differences are valid there)."""
    p, f, s = c["points"], c["flow"], c["spacing"]
    keep = torch.ones(p.shape[0], dtype=torch.bool)
    for k, d in enumerate(c["dts"]):
        o = torch.tensor(c["origins"][3 * k:3 * k + 3], dtype=p.dtype)
        u = (p + c["time_offsets"][k] * f - o) / s
        frac = u - u.floor()
        keep &= ((frac > margin) & (frac < 1 - margin)).all(dim=1)
        v = ref.trilinear_gather(d[None].double(), p + c["time_offsets"][k] * f, o.tolist(), s)[:, 0]
        keep &= (v - c["truncation"]).abs() > 1e-3
    return keep


def test_gradcheck_float64():
    c = make_case(3, 400, torch.float64, seed=5)
    keep = _far_from_kinks(c)
    assert int(keep.sum()) >= 20
    idx = keep.nonzero()[:, 0][:40]
    p, f = c["points"][idx].clone(), c["flow"][idx].clone().requires_grad_(True)
    rest = (c["dts"], c["origins"], c["spacing"], c["time_offsets"], c["weights"], c["truncation"])
    assert torch.autograd.gradcheck(lambda fl: ops.dt_loss(p, fl, *rest), (f,), eps=1e-6, atol=1e-7)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fwd_bwd_equals_separate_passes(dtype):
    c = make_case(4, 2500, dtype, seed=21)
    loss, grad = ops.dt_loss_fwd_bwd(*args(c))
    assert torch.equal(loss, ops.dt_loss(*args(c)))
    one = torch.ones((), dtype=dtype)
    assert torch.equal(grad, ops.dt_loss_backward(one, *args(c)))
    l2, g2 = dt_loss_fwd_bwd(*args(c))  # public checked wrapper
    assert torch.equal(l2, loss) and torch.equal(g2, grad)


def test_empty_point_set():
    c = make_case(2, 0, torch.float32, seed=1)
    loss, grad = ops.dt_loss_fwd_bwd(*args(c))
    assert loss.item() == 0.0 and grad.shape == (0, 3)
    assert ops.dt_loss_backward(torch.ones(()), *args(c)).shape == (0, 3)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_zero_flow_and_empty_dt_give_finite_gradients(dtype):
    c = make_case(3, 1000, dtype, seed=9)
    zero = torch.zeros_like(c["flow"])
    loss, grad = ops.dt_loss_fwd_bwd(*args(c, zero))
    assert torch.isfinite(loss) and torch.isfinite(grad).all()
    torch.testing.assert_close(loss, ref.dt_loss(*args(c, zero)), **tol(dtype))
    # a scan with no occupied sample has an all-inf DT: it must contribute exactly 0
    c["dts"][1] = ref.edt(torch.zeros(3, 4, 5, dtype=torch.bool))
    loss, grad = ops.dt_loss_fwd_bwd(*args(c))
    assert torch.isfinite(loss) and torch.isfinite(grad).all()
    c2 = dict(c, dts=[c["dts"][0], c["dts"][2]], origins=c["origins"][:3] + c["origins"][6:],
              time_offsets=[c["time_offsets"][0], c["time_offsets"][2]], weights=[c["weights"][0], c["weights"][2]])
    l2, g2 = ops.dt_loss_fwd_bwd(*args(c2))
    torch.testing.assert_close(loss, l2, **tol(dtype))
    torch.testing.assert_close(grad, g2, **tol(dtype))


def test_deterministic_across_thread_counts():
    c = make_case(4, 20000, torch.float32, seed=4)
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        a = ops.dt_loss_fwd_bwd(*args(c))
        torch.set_num_threads(max(2, old))
        b = ops.dt_loss_fwd_bwd(*args(c))
    finally:
        torch.set_num_threads(old)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_max_scans_and_shared_grid():
    c = make_case(1, 300, torch.float64, seed=2)
    K = 32
    big = dict(c, dts=c["dts"] * K, origins=c["origins"] * K, time_offsets=[0.1 * k - 1.5 for k in range(K)],
               weights=[1.0 / K] * K)
    torch.testing.assert_close(ops.dt_loss(*args(big)), ref.dt_loss(*args(big)), rtol=1e-10, atol=1e-12)


def test_opcheck():
    c = make_case(2, 50, torch.float64, seed=8)
    torch.library.opcheck(ops.dt_loss.default, args(c))
    torch.library.opcheck(ops.dt_loss_backward.default, (torch.ones((), dtype=torch.float64),) + args(c))
    torch.library.opcheck(ops.dt_loss_fwd_bwd.default, args(c))


def test_points_not_differentiable():
    c = make_case(1, 10, torch.float64)
    p = c["points"].clone().requires_grad_(True)
    loss = ops.dt_loss(p, *args(c)[1:])
    with pytest.raises(RuntimeError, match="not differentiable with respect to points"):
        loss.backward()


# --- bad inputs -------------------------------------------------------------------------

def _bad(c, **kw):
    d = dict(c)
    d.update(kw)
    return args(d)


def test_bad_inputs_public_wrapper():
    c = make_case(2, 20, torch.float32, seed=1)
    nan_p = c["points"].clone()
    nan_p[3, 1] = math.nan
    with pytest.raises(ValueError, match="points contains 1 row"):
        dt_loss(*_bad(c, points=nan_p))
    nan_f = c["flow"].clone()
    nan_f[0, 0] = math.inf
    with pytest.raises(ValueError, match="flow contains 1 row"):
        dt_loss(*_bad(c, flow=nan_f))
    with pytest.raises(TypeError, match="flow is torch.float64"):
        dt_loss(*_bad(c, flow=c["flow"].double()))
    with pytest.raises(ValueError, match="origins needs 6 values"):
        dt_loss(*_bad(c, origins=c["origins"][:5]))
    with pytest.raises(ValueError, match="at most 32"):
        dt_loss(*_bad(c, dts=[c["dts"][0]] * 33, origins=[0.0] * 99, time_offsets=[0.0] * 33, weights=[1.0] * 33))
    with pytest.raises(ValueError, match=r"dts\[1\] must be a non-empty float32"):
        dt_loss(*_bad(c, dts=[c["dts"][0], c["dts"][1].double()]))
    with pytest.raises(ValueError, match="truncation must be positive"):
        dt_loss(*_bad(c, truncation=0.0))


def test_bad_inputs_raw_op():
    c = make_case(2, 20, torch.float32, seed=1)
    with pytest.raises(RuntimeError, match="flow is Double but points is Float|points is Float but flow is Double"):
        ops.dt_loss(*_bad(c, flow=c["flow"].double()))
    with pytest.raises(RuntimeError, match="origins needs 3 values per distance transform"):
        ops.dt_loss(*_bad(c, origins=c["origins"] + [0.0]))
    with pytest.raises(RuntimeError, match="time_offsets needs 2 values"):
        ops.dt_loss_fwd_bwd(*_bad(c, time_offsets=[1.0]))
    with pytest.raises(RuntimeError, match="weights needs 2 values"):
        ops.dt_loss_backward(torch.ones(()), *_bad(c, weights=[1.0, 2.0, 3.0]))
    with pytest.raises(RuntimeError, match="at most 32"):
        ops.dt_loss(*_bad(c, dts=[c["dts"][0]] * 33, origins=[0.0] * 99, time_offsets=[0.0] * 33,
                          weights=[1.0] * 33))
    with pytest.raises(RuntimeError, match="at least one"):
        ops.dt_loss(*_bad(c, dts=[], origins=[], time_offsets=[], weights=[]))
    with pytest.raises(RuntimeError, match=r"dts\[0\] must be float32"):
        ops.dt_loss(*_bad(c, dts=[c["dts"][0].half(), c["dts"][1]]))
    with pytest.raises(RuntimeError, match=r"dts\[1\] must be a \(Z, Y, X\) grid"):
        ops.dt_loss(*_bad(c, dts=[c["dts"][0], c["dts"][1][0]]))
    with pytest.raises(RuntimeError, match=r"dts\[1\] must not be empty"):
        ops.dt_loss(*_bad(c, dts=[c["dts"][0], torch.zeros(0, 3, 3)]))
    with pytest.raises(RuntimeError, match="points must have shape"):
        ops.dt_loss(*_bad(c, points=c["points"][:, :2]))
    with pytest.raises(RuntimeError, match="flow must have the shape of points"):
        ops.dt_loss(*_bad(c, flow=c["flow"][:5]))
    with pytest.raises(RuntimeError, match="spacing must be positive"):
        ops.dt_loss(*_bad(c, spacing=-1.0))
    with pytest.raises(RuntimeError, match="truncation must be positive"):
        ops.dt_loss(*_bad(c, truncation=math.nan))
    with pytest.raises(RuntimeError, match="origins must be finite"):
        ops.dt_loss(*_bad(c, origins=[math.nan] + c["origins"][1:]))
    with pytest.raises(RuntimeError, match="grad must be a scalar"):
        ops.dt_loss_backward(torch.ones(2), *args(c))


@cuda
@needs_cuda
def test_mismatched_devices():
    c = make_case(2, 20, torch.float32, seed=1)
    with pytest.raises(RuntimeError, match="is on"):
        ops.dt_loss(*_bad(c, flow=c["flow"].cuda()))
    with pytest.raises(RuntimeError, match=r"dts\[1\] is on cpu"):
        ops.dt_loss(*_bad(c, points=c["points"].cuda(), flow=c["flow"].cuda(), dts=[c["dts"][0].cuda(), c["dts"][1]]))
    with pytest.raises(RuntimeError, match="grad is on"):
        ops.dt_loss_backward(torch.ones(()), *_bad(c, points=c["points"].cuda(), flow=c["flow"].cuda(),
                                                   dts=[d.cuda() for d in c["dts"]]))
    with pytest.raises(ValueError, match="one device"):
        dt_loss(*_bad(c, dts=[c["dts"][0], c["dts"][1].cuda()]))


# --- CUDA ---------------------------------------------------------------------------------

@cuda
@needs_cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("K,n", [(1, 0), (1, 1), (2, 777), (4, 50000)])
def test_cuda_matches_cpu(dtype, K, n):
    c = make_case(K, n, dtype, seed=31 + K)
    loss_c, grad_c = ops.dt_loss_fwd_bwd(*args(c))
    g = dict(c, points=c["points"].cuda(), flow=c["flow"].cuda(), dts=[d.cuda() for d in c["dts"]])
    loss_g, grad_g = ops.dt_loss_fwd_bwd(*args(g))
    assert loss_g.device.type == "cuda" and loss_g.dtype == dtype and loss_g.shape == ()
    torch.testing.assert_close(loss_g.cpu(), loss_c, **tol(dtype))
    if dtype == torch.float64:
        torch.testing.assert_close(grad_g.cpu(), grad_c, **tol(dtype))
    else:  # FMA contraction on the GPU can move a rare point into the neighbouring cell
        bad = ~torch.isclose(grad_g.cpu(), grad_c, rtol=1e-4, atol=1e-5).all(dim=1)
        assert int(bad.sum()) <= max(2, n // 10000)
    torch.testing.assert_close(ops.dt_loss(*args(g)).cpu(), loss_c, **tol(dtype))
    gb = ops.dt_loss_backward(torch.full((), 2.0, dtype=dtype, device="cuda"), *args(g))
    torch.testing.assert_close(gb, 2 * grad_g, **tol(dtype))
    # autograd path and determinism of the GPU reduction
    f = g["flow"].clone().requires_grad_(True)
    ops.dt_loss(*args(g, f)).backward()
    torch.testing.assert_close(f.grad, grad_g, **tol(dtype))
    assert torch.equal(ops.dt_loss_fwd_bwd(*args(g))[0], loss_g)


@cuda
@needs_cuda
def test_cuda_opcheck_and_bad_inputs():
    c = make_case(2, 100, torch.float32, seed=8, device="cuda")
    torch.library.opcheck(ops.dt_loss.default, args(c))
    torch.library.opcheck(ops.dt_loss_fwd_bwd.default, args(c))
    with pytest.raises(RuntimeError, match="at most 32"):
        ops.dt_loss(*_bad(c, dts=[c["dts"][0]] * 33, origins=[0.0] * 99, time_offsets=[0.0] * 33,
                          weights=[1.0] * 33))
    with pytest.raises(RuntimeError, match=r"dts\[0\] must be float32"):
        ops.dt_loss(*_bad(c, dts=[c["dts"][0].double(), c["dts"][1]]))
