"""A KITTI-style sequence whose sensor moves 6 m a frame (tests of the chunks' anchors: frames
of one chunk snap to different points of the 10 m anchor grid)."""

import numpy as np

from floxels_ext.lidar.preprocess import transform_points


def moving_kitti_sequence(root, n: int, seed: int = 5):
    """``root/velodyne/NNNNNN.bin`` (sensor frame) and ``root/poses.txt``; returns both paths."""
    from floxels_ext.evaluation.sim import simulate_sequence

    sim = simulate_sequence("highway", n, seed, beams=16, azimuth_steps=360)
    velo = root / "velodyne"
    velo.mkdir(parents=True)
    poses = []
    for i, fr in enumerate(sim.frames):
        pose = fr.pose.copy()
        pose[0, 3] += 6.0 * i  # the world moves with the sensor: the scans stay the same in its frame
        p = transform_points(fr.points, np.linalg.inv(fr.pose))
        np.c_[p, np.zeros(len(p))].astype(np.float32).tofile(velo / f"{i:06d}.bin")
        poses.append(pose[:3].reshape(-1))
    np.savetxt(root / "poses.txt", np.stack(poses))
    return velo, root / "poses.txt"
