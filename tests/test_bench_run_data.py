"""bench/bench_run.py's ``--data`` (tools/ab_bench.py's runs share one simulated sequence): built
once, reused when it names the same sequence, refused when it holds another or foreign files."""

import importlib.util
import sys
import types
from pathlib import Path

import pytest


def _bench_run():
    root = Path(__file__).resolve().parents[1] / "bench"
    sys.path.insert(0, str(root))  # (bench_run imports its neighbours)
    try:
        spec = importlib.util.spec_from_file_location("bench_run_under_test", root / "bench_run.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(root))
    return mod


def test_data_built_once_then_reused_and_checked(tmp_path):
    br = _bench_run()
    args = lambda **kw: types.SimpleNamespace(**{"frames": 3, "beams": 16, "azimuth": 90, "seed": 0,
                                                  "data": tmp_path / "d", **kw})
    kitti, av2, npts, how = br.built(args(), tmp_path / "t1")
    assert how == "built" and len(list((kitti / "velodyne").glob("*.bin"))) == 3 and npts > 0
    stamp = (kitti / "velodyne" / "000000.bin").stat().st_mtime_ns
    kitti2, av22, npts2, how2 = br.built(args(), tmp_path / "t2")
    assert how2.startswith("reused") and (kitti2, av22, npts2) == (kitti, av2, npts)
    assert (kitti / "velodyne" / "000000.bin").stat().st_mtime_ns == stamp  # not written again
    with pytest.raises(SystemExit, match="another sequence"):
        br.built(args(frames=4), tmp_path / "t3")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "x.txt").write_text("mine")
    with pytest.raises(SystemExit, match="not empty"):
        br.built(args(data=tmp_path / "other"), tmp_path / "t4")
    # without --data: built in the run's temporary folder
    _, _, _, how3 = br.built(args(data=None), tmp_path / "t5")
    assert how3 == "built" and (tmp_path / "t5" / "kitti" / "poses.txt").is_file()
