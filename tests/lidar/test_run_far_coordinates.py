"""``floxels run --preset accurate`` on sweeps whose poses are far from the origin (a map frame
at UTM scale) gives the flow of the same sweeps with poses near it, bit for bit (issue 46): each
chunk's world frame is re-centred on a 10 m grid point near its first pose, and the sensor
positions and the removed ground that the preset's sights read must move with the scans.

The street (KITTI-like sweeps in the sensor frame, a poses file): the ego drives along x at
1.5 m/frame between two walls seen 16 m either way of each sensor (their visible part follows the
sensor, which the sights must see through); an oncoming car; a pedestrian crossing in front on a
road that preprocessing removes (it keeps its motion only through the road returns in the range
images)."""

import numpy as np
import pytest

from floxels_ext import cli
from floxels_ext.lidar.io.outputs import read_flow_output

EGO = 1.5          # m/frame along x
CAR = -1.0         # m/frame along x, in the lane at y = -2
WALKER = 0.3       # m/frame along y, 8 m ahead of the middle frame's sensor
FAR = np.array([4e5, 5e6, 0.0])  # a multiple of the anchor grid (10 m): the chunk frames coincide
N = 7


def street_world(i, g):
    """Frame ``i``'s points in the world frame (sensor at (EGO i, 0, 1.73)) and their labels
    (0 wall, 1 car, 2 pedestrian, 3 road)."""
    sx = EGO * i
    parts, labels = [], []
    for y in (4.0, -6.0):  # the walls, 0-2 m high, seen 16 m either way: the part seen follows the sensor
        x = g.uniform(sx - 16, sx + 16, 3000)
        parts.append(np.stack([x, y + g.normal(0, 0.01, x.size), g.uniform(0, 2, x.size)], 1))
        labels.append(np.zeros(x.size, int))
    u = g.uniform(-1, 1, (1200, 3)) * [2.0, 0.9, 0.75]
    face = g.integers(0, 3, len(u))
    u[np.arange(len(u)), face] = np.sign(u[np.arange(len(u)), face]) * np.array([2.0, 0.9, 0.75])[face]
    parts.append(u + [6.0 + EGO * (N // 2) + CAR * (i - N // 2), -2.0, 0.75])
    labels.append(np.ones(len(u), int))
    body = g.uniform(-1, 1, (400, 3)) * [0.25, 0.25, 0.85] + [0.0, 0.0, 0.85]
    parts.append(body + [8.0 + EGO * (N // 2), 1.0 + WALKER * (i - N // 2), 0.0])
    labels.append(np.full(len(body), 2))
    xr, yr = np.meshgrid(np.arange(sx - 16, sx + 30, 0.35), np.arange(-5.8, 3.8, 0.35), indexing="ij")
    parts.append(np.stack([xr.ravel(), yr.ravel(), np.zeros(xr.size)], 1))
    labels.append(np.full(xr.size, 3))
    return np.concatenate(parts), np.concatenate(labels)


def write_street(d, shift=np.zeros(3)):
    """The sweeps (sensor frame, .bin) and poses (KITTI poses.txt, translations + ``shift``);
    returns (velodyne directory, poses file, labels of each frame's points)."""
    g = np.random.default_rng(0)
    (d / "velodyne").mkdir(parents=True)
    poses, labels = [], []
    for i in range(N):
        pts, lab = street_world(i, g)
        sensor = np.array([EGO * i, 0.0, 1.73])
        (pts - sensor).astype(np.float32).tofile(d / "velodyne" / f"{i:06d}.bin")  # x y z ... 3 columns
        pose = np.eye(4)[:3]
        pose[:, 3] = sensor + shift
        poses.append(pose.reshape(12))
        labels.append(lab)
    np.savetxt(d / "poses.txt", np.array(poses))
    return d / "velodyne", d / "poses.txt", labels


def run_street(tmp_path, name, shift, *extra, frames=(2, 5)):
    """``floxels run`` of the street with the accurate preset (5-scan windows, by default frames
    2-4: three windows); {frame: (flow, mask)} and the labels."""
    sweeps, poses, labels = write_street(tmp_path / name, shift)
    out = tmp_path / f"out_{name}"
    rc = cli.main(["run", str(sweeps), "--out", str(out), "--poses", str(poses), "--bin-columns", "3",
                   "--preset", "accurate", "--scans", "5", "--frames", f"{frames[0]}:{frames[1]}",
                   "--device", "cpu", "-q", *extra])
    assert rc == 0
    flows = {}
    for i in range(*frames):
        d = read_flow_output(out / f"{i:06d}.npz")
        flows[i] = (d["flow"], d["mask"])
    return flows, labels


@pytest.fixture(scope="module")
def near(tmp_path_factory):
    return run_street(tmp_path_factory.mktemp("near"), "near", np.zeros(3))


def test_accurate_run_on_the_street(near):
    """What the sights are for: walls still, the car and the pedestrian moving (in each sweep's
    sensor frame the ego's own motion is compensated: static = 0)."""
    flows, labels = near
    for i, (flow, mask) in flows.items():
        lab = labels[i]
        wall, car, walker = (mask & (lab == k) for k in range(3))
        assert wall.sum() > 1000 and car.sum() > 300 and walker.sum() > 100
        assert not (mask & (lab == 3)).any()  # the road was removed as ground
        assert np.mean(np.linalg.norm(flow[wall], axis=1) < 0.05) > 0.95
        np.testing.assert_allclose(np.median(flow[car], 0), [CAR, 0, 0], atol=0.1)
        np.testing.assert_allclose(np.median(flow[walker], 0), [0, WALKER, 0], atol=0.05)


def test_far_poses_give_the_same_flow_bit_for_bit(tmp_path, near):
    far, _ = run_street(tmp_path, "far", FAR)
    for i, (flow, mask) in near[0].items():
        assert np.array_equal(far[i][1], mask)
        assert np.array_equal(far[i][0], flow), f"frame {i}: {np.abs(far[i][0] - flow).max()} m apart"


def test_without_the_sights_the_walls_follow_the_sensor(tmp_path):
    """The scene is one where the sights matter: without them the walls keep the sensor's motion."""
    flows, labels = run_street(tmp_path, "blind", np.zeros(3), "--option", "visibility=false", "--option",
                               "range_mask=false", frames=(3, 4))
    flow, mask = flows[3]
    wall = mask & (labels[3] == 0)
    assert np.median(np.linalg.norm(flow[wall], axis=1)) > 1.0
