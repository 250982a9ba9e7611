import math

import numpy as np
import pytest

from floxels_ext.evaluation import sim
from floxels_ext.evaluation.seqio import load_sequence, read_frame, write_frame
from floxels_ext.evaluation.sim import Frame, LidarConfig, Scene, Track, simulate_sequence
from floxels_ext.evaluation.sim.lidar import BoxSet, cast_scan
from floxels_ext.evaluation.sim.scene import CAR, PEDESTRIAN

SCENES = ["urban", "highway", "crossing", "parking"]


@pytest.fixture(scope="module")
def urban():
    return simulate_sequence("urban", num_frames=3, seed=3, small=True)


def test_frame_fields_and_types(urban):
    assert len(urban.frames) == 3
    for f in urban.frames:
        n = len(f)
        assert n > 1000
        assert f.points.shape == (n, 3) and f.points.dtype == np.float32
        assert f.flow.shape == (n, 3) and f.flow.dtype == np.float32
        assert f.classes.shape == (n,) and f.classes.min() >= 0 and f.classes.max() <= 4
        assert f.instance.shape == (n,)
        assert f.dynamic.dtype == bool and f.ground.dtype == bool
        assert f.pose.shape == (4, 4)
        np.testing.assert_array_equal(f.dynamic, np.linalg.norm(f.flow, axis=1) > 0.05)
        # background has no instance and never moves (ego-motion compensated world frame)
        bg = f.classes == 0
        assert np.all(f.instance[bg] == -1) and np.all(f.instance[~bg] >= 0)
        assert np.all(f.flow[bg] == 0)
        # ground points lie on z = 0 up to range noise and are background
        assert np.all(f.classes[f.ground] == 0)
        assert np.abs(f.points[f.ground, 2]).max() < 0.15


def test_geometry_is_plausible(urban):
    f = urban.frames[0]
    origin = f.pose[:3, 3]
    assert origin[2] == pytest.approx(1.8)
    r = np.linalg.norm(f.points - origin, axis=1)
    assert r.min() >= 2.0 - 0.1 and r.max() <= 70.0 + 0.1
    assert f.dynamic.sum() > 50  # some moving objects are visible
    assert set(np.unique(f.classes)) >= {0, 1}


def test_deterministic_and_seed_dependent():
    a = simulate_sequence("crossing", 2, seed=5, small=True)
    b = simulate_sequence("crossing", 2, seed=5, small=True)
    c = simulate_sequence("crossing", 2, seed=6, small=True)
    for fa, fb in zip(a.frames, b.frames):
        np.testing.assert_array_equal(fa.points, fb.points)
        np.testing.assert_array_equal(fa.flow, fb.flow)
    assert len(a.frames[0]) != len(c.frames[0]) or not np.array_equal(a.frames[0].points, c.frames[0].points)


@pytest.mark.parametrize("scene", SCENES)
def test_all_scenes_have_motion(scene):
    seq = simulate_sequence(scene, 2, seed=0, small=True)
    f = seq.frames[0]
    assert len(f) > 1000
    assert f.dynamic.any()
    assert (f.classes > 0).any()


def test_flow_is_rigid_and_consistent_with_next_frame():
    """Flow of an object's points equals its box motion: a point's instance-local coordinates stay fixed."""
    scene = Scene("t", Track(0, 0, 0, 0))
    # car 15 m ahead driving a left arc; it stays inside the field of view
    scene.add((4.5, 1.9, 1.6), CAR, 15.0, 3.0, 0.3, 8.0, 0.5)
    seq = simulate_sequence(scene, 2, seed=0, small=True, range_noise=0, dropout=0, vehicle_detail=False)
    dt = 0.1
    tr = scene.actors[0].track
    f = seq.frames[0]
    car = f.classes == CAR
    assert car.sum() > 20
    m0, m1 = tr.matrix(0.0, 0.8), tr.matrix(dt, 0.8)
    p = f.points[car].astype(np.float64)
    moved = p + f.flow[car]
    local0 = (p - m0[:3, 3]) @ m0[:3, :3]
    local1 = (moved - m1[:3, 3]) @ m1[:3, :3]
    np.testing.assert_allclose(local0, local1, atol=1e-4)
    # speed 8 m/s at 10 Hz: about 0.8 m per frame, and the car rotates (non-uniform flow)
    speeds = np.linalg.norm(f.flow[car], axis=1)
    assert np.all(np.abs(speeds - 0.8) < 0.1) and speeds.std() > 1e-4
    # the points lie on the box surface
    assert np.all(np.abs(local0) <= np.array([2.25, 0.95, 0.8]) + 1e-4)


def test_last_frame_has_flow_and_world_frame_is_shared():
    scene = Scene("t", Track(0, 0, 0, 10.0))  # ego drives, a wall stays put
    scene.add((2.0, 30.0, 5.0), 0, 20.0, 0.0)
    seq = simulate_sequence(scene, 3, seed=0, small=True, range_noise=0, dropout=0)
    for f in seq.frames:
        wall = ~f.ground
        # the wall's near face is at x = 19 in the world frame, whatever the ego position
        np.testing.assert_allclose(f.points[wall, 0], 19.0, atol=1e-4)
        assert np.all(f.flow == 0)
    np.testing.assert_allclose(seq.frames[2].pose[0, 3], 2.0)


def test_pedestrian_walks():
    scene = Scene("t", Track(0, 0, 0, 0))
    scene.add((0.6, 0.6, 1.75), PEDESTRIAN, 6.0, 0.0, math.pi / 2, 1.5)
    f = simulate_sequence(scene, 1, seed=0, small=True, range_noise=0, dropout=0).frames[0]
    ped = f.classes == PEDESTRIAN
    assert ped.sum() > 5
    np.testing.assert_allclose(f.flow[ped], np.tile([0, 0.15, 0], (ped.sum(), 1)), atol=1e-5)
    assert np.all(f.dynamic[ped])


def test_ray_box_slab_hits_nearest_face():
    cfg = LidarConfig(beams=3, azimuth_steps=8, fov_down=-1, fov_up=1, min_range=0)
    boxes = BoxSet(np.array([[10.0, 0, 1.8], [5.0, 0, 1.8]]), np.array([[1.0, 1, 1], [0.5, 0.5, 0.5]]), np.zeros(2))
    t, hit, dirs = cast_scan(cfg, np.array([0, 0, 1.8]), 0.0, boxes)
    assert hit[1, 0] == 1 and t[1, 0] == pytest.approx(4.5)  # nearer box occludes the farther
    # looking backwards: the level and upward beams see nothing, the downward one the ground
    assert hit[1, 4] == -1 and hit[2, 4] == -1
    assert hit[0, 4] == -2 and t[0, 4] == pytest.approx(1.8 / math.sin(math.radians(1)))


def test_options_validation():
    with pytest.raises(TypeError, match="unknown"):
        simulate_sequence("urban", 1, bogus=3)
    with pytest.raises(ValueError, match="unknown scene"):
        simulate_sequence("moon", 1)
    with pytest.raises(ValueError):
        simulate_sequence("urban", 0)
    with pytest.raises(ValueError):
        LidarConfig(beams=0)


def test_save_load_roundtrip(tmp_path, urban):
    urban.save(tmp_path / "seq")
    files = sorted(p.name for p in (tmp_path / "seq").iterdir())
    assert files == ["000000.npz", "000001.npz", "000002.npz", "sequence.json"]
    back = load_sequence(tmp_path / "seq")
    assert back.meta["scene"] == "urban" and back.meta["seed"] == 3
    for a, b in zip(urban.frames, back.frames):
        for key in ("points", "flow", "classes", "instance", "dynamic", "ground", "pose"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    f = read_frame(tmp_path / "seq" / "000001.npz")
    assert isinstance(f, Frame)
    write_frame(tmp_path / "pred" / "000000.npz", flow=np.zeros((4, 3)))
    assert set(read_frame(tmp_path / "pred" / "000000.npz", require=("flow",))) == {"flow"}


def test_public_names():
    for name in ("simulate_sequence", "Frame", "Sequence", "LidarConfig", "SMALL_LIDAR", "SCENES"):
        assert hasattr(sim, name)


def test_scene_add_rejects_colliding_actors():
    scene = Scene("t", Track(0, 0, 0, 5.0), horizon=1.0)
    assert scene.add((4.5, 1.9, 1.6), CAR, 6.0, 0.0) is None  # parked where the ego drives into it
    assert scene.add((4.5, 1.9, 1.6), CAR, 12.0, 0.0) is not None
    assert scene.add((0.6, 0.6, 1.75), PEDESTRIAN, 12.0, -2.5, math.pi / 2, 1.5) is None  # walks into it
    assert scene.add((0.6, 0.6, 1.75), PEDESTRIAN, 12.0, -2.5, -math.pi / 2, 1.5).instance == 1
    assert scene.add((50, 10, 10), 0, 0.0, 0.0) is not None  # background is never checked


@pytest.mark.parametrize("scene", SCENES)
def test_scene_layouts_are_collision_free(scene):
    from floxels_ext.evaluation.sim.scene import _obb_overlap

    for seed in range(3):
        s = sim.build_scene(scene, np.random.default_rng(seed), horizon=1.4)
        fg = [a for a in s.actors if a.cls != 0]
        ts = np.linspace(0, 1.4, 15)
        poses = np.stack([a.track.poses(ts) for a in fg] + [s.ego.poses(ts)])
        sizes = np.array([a.size[:2] for a in fg] + [(4.6, 1.9)])
        hit = _obb_overlap(poses[:, None], sizes[:, None, None], poses[None], sizes[None, :, None]).any(-1)
        np.fill_diagonal(hit, False)
        assert not hit.any()
        assert len({a.instance for a in fg}) == len(fg)


# ----------------------------------------------------------------------------- vehicle detail
def _union_surface_distance(q: np.ndarray, parts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point: distance to the nearest part (0 on or in one) and depth inside the deepest part."""
    rel = np.abs(q[:, None, :] - parts[None, :, :3]) - parts[None, :, 3:]  # (N, P, 3)
    outside = np.linalg.norm(np.maximum(rel, 0), axis=-1).min(axis=1)
    inside = np.maximum((-rel).min(axis=-1), 0).max(axis=1)
    return outside, inside


@pytest.mark.parametrize("size,cls,instance_pad", [((4.6, 1.9, 1.5), CAR, 0), ((4.6, 1.9, 1.5), CAR, 3),
                                                   ((12.0, 2.55, 3.2), 2, 0), ((14.0, 2.5, 3.8), 2, 0)])
def test_detailed_vehicle_flow_is_exact_rigid_motion_onto_its_surface(size, cls, instance_pad):
    """Points of a moving vehicle shifted by their GT flow lie on the vehicle's surface at t + dt."""
    from floxels_ext.evaluation.sim import actor_parts

    scene = Scene("t", Track(0, 0, 0, 0))
    for i in range(instance_pad):  # parked far behind the sensor: picks the car shape (sedan/pickup)
        scene.add((4.5, 1.9, 1.5), CAR, -60.0 - 6 * i, 30.0)
    scene.add(size, cls, 4.0, 7.0, 0.2, 9.0, 0.3)  # passing on the left, turning
    car = scene.actors[-1]
    parts = actor_parts([car])[0]
    assert parts is not None and len(parts) >= 12
    dt = 0.1
    for noise, tol in ((0.0, 1e-4), (0.02, 0.12)):
        f = simulate_sequence(scene, 1, seed=0, range_noise=noise, dropout=0,
                              beams=64, azimuth_steps=1024).frames[0]
        sel = f.instance == car.instance
        assert sel.sum() > 200
        m0 = car.track.matrix(0.0, car.z + size[2] / 2)
        m1 = car.track.matrix(dt, car.z + size[2] / 2)
        p = f.points[sel].astype(np.float64)
        local0 = (p - m0[:3, 3]) @ m0[:3, :3]
        local1 = (p + f.flow[sel] - m1[:3, 3]) @ m1[:3, :3]
        np.testing.assert_allclose(local0, local1, atol=1e-4)  # rigid: local coordinates kept
        out, inside = _union_surface_distance(local1, parts)
        assert out.max() < tol and inside.max() < tol  # on the surface of the parts' union


def _side_depth_profile(vehicle_detail: bool):
    """Depth (m behind the body side) of a parked sedan's near side, median per (x, z) cell."""
    scene = Scene("t", Track(0, 0, 0, 0))
    scene.add((4.6, 1.9, 1.5), CAR, 0.0, 7.0, 0.0)
    f = simulate_sequence(scene, 1, seed=0, range_noise=0, dropout=0, vehicle_detail=vehicle_detail).frames[0]
    p = f.points[f.classes == CAR]
    depth = p[:, 1] - (7.0 - 0.95)
    xs, zs = np.arange(-2.0, 2.01, 0.4), np.array([0.25, 0.55, 0.85, 1.15, 1.35])
    prof = np.full((len(zs) - 1, len(xs) - 1), np.nan)
    for i in range(len(zs) - 1):
        for j in range(len(xs) - 1):
            m = (p[:, 2] >= zs[i]) & (p[:, 2] < zs[i + 1]) & (p[:, 0] >= xs[j]) & (p[:, 0] < xs[j + 1])
            if m.sum() >= 3:
                prof[i, j] = np.median(depth[m])
    return prof


def test_vehicle_side_has_shape_features_along_and_across():
    detailed, boxes = _side_depth_profile(True), _side_depth_profile(False)
    assert np.nanmax(np.abs(boxes)) < 1e-3  # the old box: one flat plane
    # along the car (the direction it would move in) the side is not flat: arches, pillars, hood
    along = np.nanmax(detailed, axis=1) - np.nanmin(detailed, axis=1)
    assert along.max() > 0.1
    # and the vertical profile is not flat either: glass set back above the belt line
    across = np.nanmax(detailed, axis=0) - np.nanmin(detailed, axis=0)
    assert np.nanmedian(across) > 0.1


def test_every_vehicle_gets_a_shape_within_its_margin():
    from floxels_ext.evaluation.sim.vehicles import parts_extent, vehicle_kind, vehicle_parts

    kinds = set()
    for name in SCENES:
        s = sim.build_scene(name, np.random.default_rng(1), horizon=1.4)
        for a in s.actors:
            parts = vehicle_parts(a)
            assert (parts is None) == (a.cls not in (1, 2))
            if parts is None:
                continue
            kinds.add(vehicle_kind(a))
            ext = parts_extent(parts)
            half = np.array(a.size) / 2
            assert np.all(ext[:2] <= half[:2] + 0.2) and ext[2] <= half[2] + 1e-9  # mirrors: < 0.3 m margin
            assert np.all(parts[:, 3:] > 0)
    assert kinds == {"sedan", "hatchback", "pickup", "van", "bus", "truck"}


# sha-free summary of the box-only simulator's output before vehicle detail existed
# (points/frame, sum |points|, sum |flow|, sum of instance ids), scenes at seed 1, small lidar
_BOX_SIMULATOR = {
    "urban": [(15308, 194657.77882508535, 539.5260246004909, 75226), (15463, 199387.71719753568, 683.7040632918943, 66988)],
    "highway": [(13261, 192871.0989184392, 7425.030424118042, 15753), (13416, 198355.56794985404, 7941.003373861313, 18834)],
    "parking": [(15025, 413773.28212736105, 18.396854209480807, 257453), (14951, 408364.75732494413, 17.708967722632224, 258082)],
}


@pytest.mark.parametrize("scene", sorted(_BOX_SIMULATOR))
def test_vehicle_detail_false_reproduces_the_box_simulator(scene):
    seq = simulate_sequence(scene, 2, seed=1, small=True, vehicle_detail=False)
    assert seq.meta["vehicle_detail"] is False and seq.meta["lidar"]["range_noise"] == sim.LEGACY_RANGE_NOISE
    for f, (n, ps, fs, inst) in zip(seq.frames, _BOX_SIMULATOR[scene]):
        assert len(f) == n and int(f.instance.sum()) == inst
        assert float(np.abs(f.points.astype(np.float64)).sum()) == pytest.approx(ps, rel=1e-9)
        assert float(np.abs(f.flow.astype(np.float64)).sum()) == pytest.approx(fs, rel=1e-7)
    detailed = simulate_sequence(scene, 1, seed=1, small=True)
    assert detailed.meta["vehicle_detail"] is True and detailed.meta["lidar"]["range_noise"] == 0.02
    assert len(detailed.frames[0]) != _BOX_SIMULATOR[scene][0][0]


def test_cli_simulate_boxes_flag(tmp_path, capsys):
    from floxels_ext import cli

    assert cli.main(["simulate", str(tmp_path / "b"), "--scene", "highway", "--seed", "1", "--frames", "1",
                     "--small", "--boxes"]) == 0
    f = read_frame(tmp_path / "b" / "000000.npz")
    assert len(f) == _BOX_SIMULATOR["highway"][0][0]
    assert load_sequence(tmp_path / "b").meta["vehicle_detail"] is False
