"""Issue 45 item 5 through ``cli.main``: ``floxels run`` reads float64 world-frame files (map-scale
coordinates, a UTM-like offset) in float64 up to the re-centring, so the result is that of the
same scene near the origin; float32 files far out are warned about with advice that fits them.
With ``--no-ego-motion`` each scan's sensor is taken at its file frame's origin: for world-frame
files far out that is thousands of km from the points, a sensor the estimator does not use (one
warning), so ``accurate`` (the default) runs there as without its sights (issue 42)."""

import numpy as np
import pytest
from cli_doubles import main, simulated

from floxels_ext.lidar.io.outputs import read_flow_output

SHIFT = np.array([4.0e5, 5.0e6, 0.0])  # a UTM-like offset: float32 resolves 0.5 m there
RUN = ["--scans", "3", "--frames", "2:3", "--max-iters", "40", "--device", "cpu"]


@pytest.fixture
def seq():
    return simulated(5, 7)


def _write(seq, d, kind, shift, dtype=np.float64):
    d.mkdir(parents=True)
    for i, fr in enumerate(seq.frames):
        pts = (fr.points.astype(np.float64) + shift).astype(dtype)
        if kind == "npz":  # world-frame points with the sensor pose (read with --points-frame world)
            pose = fr.pose.copy()
            pose[:3, 3] += shift
            np.savez(d / f"{i:06d}.npz", points=pts, pose=pose)
        else:
            np.save(d / f"{i:06d}.npy", pts)
    return d


NO_SIGHTS = ["--option", "range_mask=false", "--option", "visibility=false"]
SENSOR_UNUSED = "more than 1000 m from every point of the scan"


@pytest.mark.parametrize("kind, extra, near_extra", [
    ("npz", ["--points-frame", "world"], []),
    # ranges from the world origin: no crop, no ground grid; the origin is no sensor far out
    ("npy", ["--no-ego-motion", "--min-range", "none", "--max-range", "none", "--max-height", "none",
             "--no-ground-removal"], NO_SIGHTS),
    ("npy", ["--no-ego-motion", "--min-range", "none", "--max-range", "none", "--max-height", "none",
             "--no-ground-removal", "--preset", "paper"], []),
])
def test_float64_world_frame_files_far_out_give_the_result_near_the_origin(seq, tmp_path, capsys, kind, extra,
                                                                             near_extra):
    flows = {}
    for name, shift, more in (("near", np.zeros(3), near_extra), ("far", SHIFT, [])):
        d = _write(seq, tmp_path / name, kind, shift)
        rc, cap = main(["run", d, "--out", tmp_path / f"o_{name}", *RUN, *extra, *more], capsys)
        assert rc == 0, cap.err
        said = 1 if name == "far" and near_extra else 0  # the world origin as sensor far out: said once
        assert cap.err.count("warning") == said and cap.err.count(SENSOR_UNUSED) == said, cap.err
        out = read_flow_output(tmp_path / f"o_{name}" / "000002.npz", points=False)
        flows[name] = out["flow"], out["mask"]
    np.testing.assert_array_equal(flows["far"][1], flows["near"][1])  # the same points kept
    np.testing.assert_allclose(flows["far"][0], flows["near"][0], atol=1e-5)  # float32: 0.5 m steps before


def test_float32_files_far_out_are_warned_about_with_fitting_advice(seq, tmp_path, capsys):
    d = _write(seq, tmp_path / "f32", "npz", SHIFT, np.float32)
    rc, cap = main(["run", d, "--out", tmp_path / "o", *RUN, "--points-frame", "world"], capsys)
    assert rc == 0, cap.err
    assert "floxels: warning:" in cap.err and "float32" in cap.err and "store them as float64" in cap.err
    assert "Pass float64 scans" not in cap.err and ".py:" not in cap.err  # not the API's advice, no source line


def test_no_ground_removed_beyond_the_grids_reach_is_said(seq, tmp_path, capsys):
    # --no-ego-motion measures from the world origin: at map scale the ground grid (200 m around
    # it) holds none of the points, and the ground used to stay in without a word
    d = _write(seq, tmp_path / "far", "npy", SHIFT)
    rc, cap = main(["run", d, "--out", tmp_path / "o", *RUN, "--no-ego-motion", "--min-range", "none",
                    "--max-range", "none", "--max-height", "none"], capsys)
    assert rc == 0 and ".npy: no ground removed" in cap.err and "beyond the ground grid's reach (200 m)" in cap.err
    assert "--no-ground-removal" in cap.err and cap.err.count("no ground removed") == 1
