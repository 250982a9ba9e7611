"""The cases of ``bench/accurate_map.py``: simulated sequences (one per beams x length x scene x
seed) and the shared real scans (the AV2 pair with labels, the KITTI sweeps without), each as an
API user passes them (scans in one world frame, each scan's pose or sensor position, its removed
ground), with the frames to score and what each frame is (its position in the sequence), and the
metrics of a group of scored frames (labelled: EPE by speed; label-free: the next-sweep check)."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from compare import load_av2_pair, load_sim_scene  # noqa: E402

from floxels_ext.evaluation.metrics import evaluate_sequence  # noqa: E402

# object speeds (m/frame) of the speed columns: slow (pedestrians, creeping), urban, fast
SPEED_BUCKETS = ((0.05, 0.5), (0.5, 1.0), (1.0, math.inf))
SCENES = ("urban", "crossing", "highway", "parking")
SHARED = HERE.parent.parent / "shared" / "data"


@dataclass
class Case:
    """One sequence to estimate: scans in one world frame and what the API takes besides them
    (``sensors``: (3,) positions, ``poses``: (4, 4) world-from-sensor, ``ground``: removed ground
    returns), the frames to score with their attributes, and per frame the truth (None: no labels,
    then ``check`` scores it: each scored frame's neighbour scan for the next-sweep check)."""

    key: str
    scans: list
    sensors: list
    poses: list
    ground: list
    frames: list[int]
    attrs: dict                       # beams, length, scene, seed, source
    truth: list | None = None
    positions: dict = field(default_factory=dict)  # frame -> "first" / "mid" / "last"


def positions(frames: list[int], length: int) -> dict:
    """Where each scored frame sits: its window is one-sided at the sequence's ends."""
    return {f: "first" if f == 0 else "last" if f == length - 1 else "mid" for f in frames}


def scored_frames(length: int, spec: str) -> list[int]:
    """Frames to score of a ``length``-scan sequence: ``ends`` (first, middle, last; default),
    ``all``, or a comma list (negative = from the end)."""
    if spec == "ends":
        return sorted({0, length // 2, length - 1})
    if spec == "all":
        return list(range(length))
    out = sorted({int(v) % length for v in spec.split(",")})
    return out


def sim_case(scene: str, seed: int, beams: int, length: int, frames_spec: str, max_range: float = 50.0,
             azimuth: int = 2048, cache: Path | None = None) -> Case:
    """A simulated sequence: ``beams`` x ``azimuth`` lidar, the paper's protocol crop. ``cache``: a
    directory keeping each simulated sequence (a pickle; the simulator is deterministic)."""
    import pickle

    path = None if cache is None else Path(cache) / f"sim_{scene}_{seed}_{beams}_{length}_{azimuth}_{max_range:g}.pkl"
    if path is not None and path.exists():
        scans, truth, sight = pickle.loads(path.read_bytes())
    else:
        scans, truth, sight = load_sim_scene(scene, seed, length, "full", max_range, 0,
                                             {"beams": beams, "azimuth_steps": azimuth})
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(pickle.dumps((scans, truth, sight)))
    frames = scored_frames(length, frames_spec)
    return Case(f"sim/b{beams}/L{length}/{scene}/s{seed}", scans, sight["sensors"], sight["poses"], sight["ground"],
                frames, {"source": "sim", "beams": beams, "length": length, "scene": scene, "seed": seed},
                truth, positions(frames, length))


def av2_case(path: str | None = None) -> Case:
    """The shared Argoverse 2 pair (compare.py's loader): a 2-scan sequence, frame 0 scored."""
    path = path or str(SHARED / "av2_pair" / "av2_7fab2350_pair.npz")
    scans, truth, sight = load_av2_pair(path)
    return Case("real/av2_pair", scans, sight["sensors"], sight["poses"], sight["ground"], [0],
                {"source": "av2", "beams": 32, "length": 2, "scene": "av2"}, truth, {0: "first"})


def read_kitti_poses(path: str) -> list[np.ndarray]:
    """KITTI odometry pose rows (12 numbers: a 3 x 4 world-from-sensor matrix) as (4, 4)."""
    rows = np.loadtxt(path, dtype=np.float64).reshape(-1, 12)
    out = []
    for r in rows:
        m = np.eye(4)
        m[:3] = r.reshape(3, 4)
        out.append(m)
    return out


def kitti_case(frames_spec: str, poses_path: str | None = None) -> Case:
    """The shared KITTI sweeps (13, label-free) with the KISS-ICP poses in bench/: each sweep
    preprocessed as ``floxels run`` does (crop 3-50 m, ground and outliers removed), kept points
    and ground moved into the world frame."""
    from floxels_ext.lidar.preprocess import GROUND, KEPT, Preprocess, preprocess_classes

    d = np.load(SHARED / "kitti_raw_13f" / "kitti_raw_2011_09_26_13f.npz")
    o = d["frame_offsets"]
    poses = read_kitti_poses(poses_path or str(HERE / "kitti_raw_13f_poses_kiss_icp.txt"))
    scans, ground = [], []
    for i in range(len(o) - 1):
        p = d["points"][o[i]:o[i + 1]].astype(np.float32)
        cls = preprocess_classes(p, Preprocess())
        T = poses[i]
        world = lambda q: np.ascontiguousarray(q.astype(np.float64) @ T[:3, :3].T + T[:3, 3], np.float32)  # noqa: E731
        scans.append(world(p[cls == KEPT]))
        ground.append(world(p[cls == GROUND]))
    n = len(scans)
    frames = scored_frames(n, frames_spec)
    return Case("real/kitti", scans, [T[:3, 3].copy() for T in poses[:n]], poses[:n], ground, frames,
                {"source": "kitti", "beams": 64, "length": n, "scene": "kitti"}, None, positions(frames, n))


def speed_epe(preds, truths) -> dict:
    """Per speed bucket (true speed, dynamic points, ground excluded): mean EPE and points."""
    out = {}
    for lo, hi in SPEED_BUCKETS:
        err, cnt = 0.0, 0
        for p, t in zip(preds, truths):
            g = np.asarray(t["flow"], np.float64)
            s = np.linalg.norm(g, axis=1)
            keep = (s >= lo) & (s < hi) & np.asarray(t["dynamic"], bool)
            if "ground" in t:
                keep &= ~np.asarray(t["ground"], bool)
            err += float(np.linalg.norm(np.asarray(p, np.float64)[keep] - g[keep], axis=1).sum())
            cnt += int(keep.sum())
        out[f"{lo:g}-{hi:g}"] = {"epe": err / cnt if cnt else None, "points": cnt}
    return out


def labelled_metrics(preds, truths) -> dict:
    m = evaluate_sequence(preds, truths)
    return {"dyn_norm": m["mean_dynamic_normalized_epe"], "static": m["static_epe"], "dyn": m["dynamic_epe"],
            "speed": speed_epe(preds, truths), "frames": len(preds)}


def next_sweep_check(points, flow, other, step: int, threshold: float = 0.05) -> tuple[int, int]:
    """(moving points, moving points in DBSCAN clusters whose flow does not bring them closer to
    the neighbour sweep ``other`` (``step`` frames away: +1 next, -1 previous; nearest-neighbour
    distance, cluster mean) than zero flow does): bench_evidence.py's label-free check."""
    import torch
    from scipy.spatial import cKDTree

    from floxels_ext.ops import dbscan

    moving = np.linalg.norm(flow, axis=1) > threshold
    tree = cKDTree(other)
    d_flow = tree.query(points + step * flow)[0]
    d_zero = tree.query(points)[0]
    labels = dbscan(torch.as_tensor(points), 0.5, 4).numpy()
    groups = np.where(labels >= 0, labels, labels.max(initial=-1) + 1 + np.arange(len(labels)))
    _, g = np.unique(groups, return_inverse=True)
    cnt = np.bincount(g)
    worse = np.bincount(g, d_flow) / cnt >= np.bincount(g, d_zero) / cnt
    return int(moving.sum()), int((moving & worse[g]).sum())


def label_free_metrics(case: Case, preds: dict) -> dict:
    """KITTI: share of moving points the neighbour sweep does not support (lower is better)."""
    mv = bad = 0
    for f, flow in preds.items():
        step = 1 if f + 1 < len(case.scans) else -1
        m, b = next_sweep_check(case.scans[f], np.asarray(flow, np.float64), case.scans[f + step], step)
        mv, bad = mv + m, bad + b
    return {"moving": mv, "unsupported": bad / mv if mv else 0.0, "frames": len(preds)}
