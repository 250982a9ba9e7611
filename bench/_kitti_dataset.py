"""A simulated dataset in the KITTI odometry layout for the dataset benches (``bench_ray.py``):
``ROOT/sequences/NN/velodyne/NNNNNN.bin`` (x y z intensity float32, each scan in its sensor
frame) with ``ROOT/poses/NN.txt``, and one long sequence ``ROOT/long/velodyne`` +
``ROOT/long/poses.txt`` holding the same frames (every distinct sequence once, one after the
other), the reference of a sequence's frames/s.

Fast: the frames of a sequence are independent once its scene is built (``simulate_sequence``
simulates frame ``i`` with its own generator), so they are simulated in parallel over
processes, ``distinct`` sequences only; the others are hard links to them (the pipeline does
the same work for a link as for a copy). The tree is reused when ``ROOT/dataset.json`` says it
was made with the same parameters.
"""

from __future__ import annotations

import json
import os
import shutil
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

SCENES = ("urban", "crossing", "highway", "parking")


def _frames(job):
    """Simulates frames [a, b) of (scene, seed) and writes them; returns their poses."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from floxels_ext.evaluation.sim import LidarConfig, actor_parts, build_scene, simulate_frame
    from floxels_ext.lidar.preprocess import transform_points

    out, scene, seed, n, a, b, beams, az = job
    cfg = LidarConfig(beams=beams, azimuth_steps=az)
    dt = 1.0 / cfg.rate_hz
    scene_obj = build_scene(scene, np.random.default_rng([seed, 0]), (n + 1) * dt)  # as simulate_sequence
    parts = actor_parts(scene_obj.actors)
    poses = []
    for i in range(a, b):
        fr = simulate_frame(scene_obj, cfg, i * dt, dt, np.random.default_rng([seed, 1, i]), parts)
        p = transform_points(fr.points, np.linalg.inv(fr.pose))
        np.c_[p, np.zeros(len(p), np.float32)].astype(np.float32).tofile(Path(out) / f"{i:06d}.bin")
        poses.append(fr.pose[:3].reshape(12))
    return a, poses


def make_kitti_dataset(root: Path, sequences: int, frames: int, beams: int, azimuth: int, procs: int,
                       distinct: int | None = None) -> dict:
    """Builds (or reuses) the dataset; returns its description (also in ROOT/dataset.json)."""
    distinct = max(1, min(distinct or sequences, sequences))
    want = dict(sequences=sequences, frames=frames, beams=beams, azimuth_steps=azimuth, distinct=distinct, layout="kitti")
    stamp = root / "dataset.json"
    if stamp.is_file() and json.loads(stamp.read_text()) == want:
        return want
    shutil.rmtree(root, ignore_errors=True)
    (root / "poses").mkdir(parents=True)
    step = max(1, min(10, frames // max(1, procs // distinct or 1)))
    jobs, dirs = [], []
    for k in range(distinct):
        d = root / "sequences" / f"{k:02d}" / "velodyne"
        d.mkdir(parents=True)
        dirs.append(d)
        for a in range(0, frames, step):
            jobs.append((str(d), SCENES[k % len(SCENES)], k, frames, a, min(frames, a + step), beams, azimuth))
    poses = {k: [None] * frames for k in range(distinct)}
    with ProcessPoolExecutor(max(1, procs)) as ex:
        for job, (a, ps) in zip(jobs, ex.map(_frames, jobs)):
            poses[int(job[2])][a:a + len(ps)] = ps
    for k in range(distinct):
        np.savetxt(root / "poses" / f"{k:02d}.txt", np.stack(poses[k]), fmt="%.9g")
    for k in range(distinct, sequences):  # hard links to the distinct ones
        src = k % distinct
        d = root / "sequences" / f"{k:02d}" / "velodyne"
        d.mkdir(parents=True)
        for i in range(frames):
            os.link(dirs[src] / f"{i:06d}.bin", d / f"{i:06d}.bin")
        shutil.copy(root / "poses" / f"{src:02d}.txt", root / "poses" / f"{k:02d}.txt")
    long = root / "long" / "velodyne"  # outside sequences/: the dataset run does not see it as a sequence
    long.mkdir(parents=True)
    j = 0
    for k in range(distinct):
        for i in range(frames):
            os.link(dirs[k] / f"{i:06d}.bin", long / f"{j:06d}.bin")
            j += 1
    np.savetxt(root / "long" / "poses.txt", np.concatenate([np.stack(poses[k]) for k in range(distinct)]), fmt="%.9g")
    stamp.write_text(json.dumps(want))
    return want
