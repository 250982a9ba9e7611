"""The ops trace through torch.compile (fake kernels + autograd registrations)."""

import torch

import floxels_ext  # noqa: F401

F = torch.ops.floxels


def test_compiled_loss_and_gradients_match_eager():
    g = torch.Generator().manual_seed(0)
    grid = torch.randn(3, 6, 7, 8, generator=g, requires_grad=True)
    pts = torch.rand(200, 3, generator=g) * torch.tensor([3.5, 3.0, 2.5])
    dt = torch.rand(10, 12, 14, generator=g) * 3
    labels = torch.randint(-1, 5, (200,), generator=g)

    def step(grid):
        flow = F.trilinear_gather(grid, pts, [0.0, 0.0, 0.0], 0.5)
        loss = F.dt_loss(pts, flow, [dt], [0.0, 0.0, 0.0], 0.3, [1.0], [1.0], 2.0)
        return loss + 0.6 * F.cluster_consistency_loss(flow, labels, 5)

    compiled = torch.compile(step, backend="aot_eager", fullgraph=True)
    eager = step(grid)
    (ge,) = torch.autograd.grad(eager, grid)
    out = compiled(grid)
    (gc,) = torch.autograd.grad(out, grid)
    torch.testing.assert_close(out, eager)
    torch.testing.assert_close(gc, ge)


def test_compiled_data_only_dt_ops_match_eager():
    g = torch.Generator().manual_seed(1)
    pts = torch.rand(300, 3, generator=g) * 3
    motion = torch.randn(300, 3, generator=g) * 0.2
    dts = [torch.rand(10, 12, 14, generator=g) * 3, torch.rand(8, 9, 10, generator=g) * 2]
    origins = [0.0, 0.0, 0.0, 0.1, -0.2, 0.0]
    cells = torch.arange(300) // 7

    def evaluate(motion):
        r = F.dt_residual(pts, motion, dts, origins, 0.3, [1.0, -1.0], [0.6, 0.4], 1.0, True)
        s = F.dt_sample(pts, motion, dts, origins, 0.3, [1.0, -1.0])
        score, explained, rf, rz = F.dt_evidence(pts, motion, None, cells, dts, origins, 0.3, [1.0, -1.0],
                                                 [0.6, 0.4], 1.0, 0.02, 0.05)
        return r + s[:, :, 1:].abs().sum((0, 2)) + torch.where(explained, score, rf - rz)

    compiled = torch.compile(evaluate, backend="aot_eager", fullgraph=True)
    torch.testing.assert_close(compiled(motion), evaluate(motion))
