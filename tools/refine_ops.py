"""How many ops and host synchronisations does one ``rigid_refine`` call take (issue 33)?

Counts the ATen ops (top-level calls, as torch.profiler records them on the CPU; "not views":
without the view and no-op ops that launch no kernel on CUDA), the
``floxels::`` ops, the index_put_ segment sums and the host read-backs (``aten::item`` /
``aten::_local_scalar_dense``, ``aten::nonzero``; on CUDA also the kernels launched) of one call of
``floxels_ext.estimator.refine.rigid_refine`` on the synthetic passing cars of
tests/estimator/test_refine.py, with 2, 4 and 8 support scans; and its wall time (median of 5).
``--search``: the call as the preset makes it, also started from the searched velocity
(``refine_search``).

    PYTHONPATH=python python tools/refine_ops.py [--device cpu|cuda] [--search] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "estimator"))
from test_refine import _labels, _supports, passing_cars  # noqa: E402

from floxels_ext.estimator.refine import rigid_refine  # noqa: E402


def case(num_supports: int, device: str):
    half = num_supports // 2
    offsets = tuple(range(-half, half + 1)) if num_supports % 2 == 0 else tuple(range(-half, half + 2))
    target = offsets.index(0)
    v = 1.2
    scans, rows = passing_cars(v, offsets)
    P = torch.from_numpy(scans[target]).to(device)
    a, b = rows[target]
    flow = torch.zeros_like(P)
    flow[a, 0], flow[b, 0] = 0.5 * v, -0.5 * v
    return P, flow, _labels(P), _supports(scans, target, offsets, device=device), (a, b, v)


VIEWS = {"aten::" + n for n in ("unsqueeze", "squeeze", "select", "slice", "view", "reshape", "expand",
                                  "expand_as", "transpose", "unbind", "detach", "as_strided", "alias", "t",
                                  "permute", "diagonal", "empty", "empty_like", "lift_fresh", "_unsafe_view",
                                  "movedim", "split", "chunk", "narrow", "to", "resolve_conj", "resolve_neg")}


def count_ops(fn, cuda: bool = False) -> Counter:
    from torch.profiler import ProfilerActivity, profile

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=acts) as prof:
        fn()
        if cuda:
            torch.cuda.synchronize()
    # top-level events only (an op's own sub-ops are not extra launches from Python)
    evs = prof.events()
    top = [e for e in evs if e.cpu_parent is None or not (e.cpu_parent.name.startswith("aten::")
                                                          or e.cpu_parent.name.startswith("floxels::"))]
    c = Counter()
    for e in top:
        if e.name.startswith(("aten::", "floxels::")):
            c["ops"] += 1
            c[e.name] += 1
            if e.name not in VIEWS or (e.name == "aten::to" and any(
                    ch.name == "aten::_to_copy" for ch in e.cpu_children)):
                c["compute"] += 1
    for e in evs:  # host read-backs, wherever they sit; CUDA kernels (memcpy/memset left out)
        if e.name in ("aten::_local_scalar_dense", "aten::nonzero"):
            c["sync:" + e.name] += 1
        if cuda and e.device_type == torch.autograd.DeviceType.CUDA and not e.name.startswith(("Memcpy", "Memset")):
            c["cuda_kernels"] += 1
    return c


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--supports", type=int, nargs="+", default=[2, 4, 8])
    ap.add_argument("--search", action="store_true", help="rigid_refine(search=True), the preset's call")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)

    def refine(P, flow, lab, sup):
        return rigid_refine(P, flow, lab, sup, search=args.search)

    out = []
    print("| supports | ops | ops not views | floxels ops | index_put_ | item (syncs) | nonzero | ms (median of 5) | max car error m |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for k in args.supports:
        P, flow, lab, sup, (a, b, v) = case(k, args.device)
        res = refine(P, flow, lab, sup)  # warm-up
        c = count_ops(lambda: refine(P, flow, lab, sup), args.device.startswith("cuda"))
        ts = []
        for _ in range(5):
            if args.device.startswith("cuda"):
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            res = refine(P, flow, lab, sup)
            if args.device.startswith("cuda"):
                torch.cuda.synchronize()
            ts.append(time.perf_counter() - t0)
        res = res.cpu().numpy()
        err = max(np.abs(res[a] - [v, 0, 0]).max(), np.abs(res[b] - [-v, 0, 0]).max())
        fl = sum(n for name, n in c.items() if name.startswith("floxels::"))
        row = {"supports": len(sup), "ops": c["ops"], "compute_ops": c["compute"], "floxels_ops": fl, "index_put_": c["aten::index_put_"],
               "item": c["sync:aten::_local_scalar_dense"], "nonzero": c["sync:aten::nonzero"],
               "ms": 1e3 * statistics.median(ts), "max_error": float(err), "cuda_kernels": c["cuda_kernels"],
               "top": dict(c.most_common(12))}
        out.append(row)
        print(f"| {row['supports']} | {row['ops']} | {row['compute_ops']} | {fl} | {row['index_put_']} | {row['item']} | {row['nonzero']} | "
              f"{row['ms']:.1f} | {err:.4f} |")
    for row in out:
        print(row["supports"], row["top"], f"CUDA kernels: {row['cuda_kernels']}" if args.device != "cpu" else "")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
