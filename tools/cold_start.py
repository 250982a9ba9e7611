"""What a cold ``floxels run`` process pays before its first frame on a GPU: importing torch and
the extension, creating the CUDA context, and the first estimates (kernel loading, allocator and
pinned-buffer growth), each timed in order in a fresh process.

    python tools/cold_start.py
"""

import time

t0 = time.perf_counter()
import torch  # noqa: E402

t1 = time.perf_counter()
import floxels_ext  # noqa: E402,F401
from floxels_ext import FloxelsConfig, estimate_flow  # noqa: E402

t2 = time.perf_counter()
torch.zeros(1, device="cuda")
torch.cuda.synchronize()
t3 = time.perf_counter()
print(f"import torch {t1 - t0:.2f} s, import floxels_ext {t2 - t1:.2f} s, CUDA context {t3 - t2:.2f} s")
rng = __import__("numpy").random.default_rng(0)
for n, iters in ((2000, 20), (2000, 20), (100_000, 500), (100_000, 500)):
    scans = [(rng.uniform(-40, 40, (n, 3)) * [1, 1, 0.05]).astype("float32") for _ in range(5)]
    t = time.perf_counter()
    estimate_flow(scans, target=2, config=FloxelsConfig(max_iters=iters), device="cuda")
    torch.cuda.synchronize()
    print(f"estimate_flow 5 x {n} points, {iters} iterations: {time.perf_counter() - t:.3f} s")
