"""``floxels run`` / ``show`` / ``accumulate`` user errors of issue 30, through ``cli.main`` (the
entry point): frames with no point left after cropping, stray far points, output paths that are
existing directories, numeric options, ``run -q``, ``show``'s input hash. A fake method (instant,
exact) stands in for Floxels."""

import json

import numpy as np
import pytest

from floxels_ext import cli, methods

N = 4


@pytest.fixture(scope="module")
def seq():
    from floxels_ext.evaluation.sim import simulate_sequence

    return simulate_sequence("crossing", N, 2, beams=16, azimuth_steps=360)


@pytest.fixture
def fake(monkeypatch):
    def est(scans, frames, device, options, callback, times=None):
        for f in frames:
            callback(f, np.tile(np.float32([0.4, 0, 0]), (len(scans[f]), 1)))

    monkeypatch.setitem(methods._REGISTRY, "fake", methods.Method("fake", "test double", est))


def _npy_dir(seq, d, shift=(0.0, 0.0, 0.0), edit=None):
    d.mkdir(parents=True, exist_ok=True)
    for i, fr in enumerate(seq.frames):
        p = fr.points + np.asarray(shift)
        if edit is not None:
            p = edit(i, p)
        np.save(d / f"{i:06d}.npy", p.astype(np.float32))
    return d


def _run(args, capsys):
    rc = cli.main(["run", *map(str, args), "--device", "cpu"])
    return rc, capsys.readouterr()


def test_world_frame_with_no_ego_motion_fails_every_emptied_frame_by_name(seq, fake, tmp_path, capsys):
    # world-frame points 300 m from the world origin read with --no-ego-motion: the 50 m crop
    # around the origin empties every frame (before: all-zero flow, "0 failed", exit 0)
    d = _npy_dir(seq, tmp_path / "in", shift=(300.0, 0.0, 0.0))
    rc, cap = _run([d, "--out", tmp_path / "out", "--method", "fake", "--no-ego-motion"], capsys)
    assert rc == 1
    assert "000002.npy: no point left to optimise after cropping" in cap.err
    assert "Likely a wrong frame" in cap.err and "--no-ego-motion measures from the world origin" in cap.err
    assert f"{N} failed ({N} with no point left after cropping)" in cap.err
    summary = json.loads((tmp_path / "out" / "run_summary.json").read_text())
    assert summary["failed"] == N and summary["no_points_after_crop"] == [f"{i:06d}" for i in range(N)]
    assert not list((tmp_path / "out").glob("*.npz"))  # no all-zero flow passed off as a result


def test_one_scan_beyond_max_range_fails_that_frame_only(seq, fake, tmp_path, capsys):
    d = _npy_dir(seq, tmp_path / "in", edit=lambda i, p: p + np.array([500.0, 0, 0]) if i == 1 else p)
    rc, cap = _run([d, "--out", tmp_path / "out", "--method", "fake", "--no-ego-motion"], capsys)
    assert rc == 1 and "1 failed (1 with no point left after cropping)" in cap.err
    assert "000001.npy: no point left" in cap.err and "000002.npy: no point" not in cap.err
    assert sorted(p.name for p in (tmp_path / "out").glob("*.npz")) == ["000000.npz", "000002.npz", "000003.npz"]
    # the same files with the crop widened: the frame is estimated
    rc, cap = _run([d, "--out", tmp_path / "out2", "--method", "fake", "--no-ego-motion", "--max-range", "none",
                    "--max-height", "none"], capsys)
    assert rc == 0, cap.err


def _main(argv, capsys):
    rc = cli.main([str(a) for a in argv])
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err
    return rc, cap


@pytest.fixture
def run_dir(seq, fake, tmp_path, capsys):
    d = _npy_dir(seq, tmp_path / "in")
    rc, cap = _run([d, "--out", tmp_path / "out", "--method", "fake", "--no-ego-motion", "-q"], capsys)
    assert rc == 0, cap.err
    # -q prints the final summary its help promises, and nothing else
    assert cap.err.startswith("done: 4 frame(s) written") and len(cap.err.strip().splitlines()) == 1
    return tmp_path / "out"


@pytest.mark.parametrize("argv, option", [
    (["show", "{run}", "--frame", "000001", "--png", "{dir}"], "--png"),
    (["accumulate", "{run}", "000001", "--out", "{dir}"], "--out"),
    (["eval", "{run}", "{run}", "--json", "{dir}"], "--json"),
    (["demo", "--png", "{dir}", "--small", "--iters", "1"], "--png"),
    (["run", "{inp}", "--out", "{tmp}/o2", "--method", "fake", "--no-ego-motion", "--summary", "{dir}"], "--summary"),
])
def test_existing_directory_as_output_file_is_refused_before_the_work(run_dir, tmp_path, capsys, argv, option):
    target = tmp_path / "taken"
    target.mkdir()
    fill = dict(run=run_dir, dir=target, inp=tmp_path / "in", tmp=tmp_path)
    rc, cap = _main([a.format(**fill) for a in argv], capsys)
    assert rc == 2 and cap.err.startswith(f"floxels: error: {option} {target} is an existing directory"), cap.err
    assert cap.out == ""  # nothing computed first
    assert not list(target.iterdir()) and not list(tmp_path.glob(".*tmp*")) and not list(run_dir.glob(".*tmp*"))
    assert not (tmp_path / "o2").exists()


@pytest.mark.parametrize("argv", [
    ["show", "{run}", "--frame", "000001", "--png", "{tmp}/f1.jpg"],
    ["demo", "--png", "{tmp}/demo.jpg", "--small", "--iters", "1"],
])
def test_a_png_under_another_name_is_refused_before_the_work(run_dir, tmp_path, capsys, argv):
    rc, cap = _main([a.format(run=run_dir, tmp=tmp_path) for a in argv], capsys)
    assert rc == 2 and cap.err.startswith("floxels: error: --png ") and "give a name ending in .png" in cap.err, cap.err
    assert cap.out == "" and not list(tmp_path.glob("*.jpg"))


@pytest.mark.parametrize("argv, message", [
    (["show", "{run}", "--frame", "1", "--flow-scale", "nan"], "argument --flow-scale: must be a finite number"),
    (["show", "{run}", "--frame", "1", "--extent", "inf"], "argument --extent: must be a finite number"),
    (["show", "{run}", "--frame", "1", "--frame-period", "-1"], "argument --frame-period: must be a finite number > 0"),
    (["show", "{run}", "--frame", "1", "--center", "nan,0"], "--center expects X,Y (two finite numbers)"),
    (["accumulate", "{run}", "1", "--out", "{tmp}/a.ply", "--radius", "-1"], "argument --radius: must be a finite "
                                                                              "number > 0, got '-1'"),
    (["accumulate", "{run}", "1", "--out", "{tmp}/a.ply", "--radius", "nan"], "argument --radius: must be a finite"),
    # ignored before: --radius without --mode chain, --no-flow with chain; > 127 neighbours wrapped
    # the int8 time_offset property around
    (["accumulate", "{run}", "1", "--out", "{tmp}/a.ply", "--radius", "2"], "--radius is the neighbour search "
                                                                             "radius of --mode chain"),
    (["accumulate", "{run}", "1", "--out", "{tmp}/a.ply", "--mode", "chain", "--no-flow"], "--no-flow merges "
                                                                                           "without moving"),
    (["accumulate", "{run}", "1", "--out", "{tmp}/a.ply", "--neighbours", "200"], "--neighbours must be in [1, "
                                                                                  "127], got 200"),
    (["simulate", "{tmp}/s", "--small", "--range-noise", "nan"], "argument --range-noise: must be a finite number"),
    (["simulate", "{tmp}/s", "--small", "--max-range", "inf"], "argument --max-range: must be a finite number"),
    (["simulate", "{tmp}/s", "--small", "--seed", "-1"], "argument --seed: must be an integer >= 0"),
    (["demo", "--seed", "-1"], "argument --seed: must be an integer >= 0"),
    (["eval", "{run}", "{run}", "--eval-box", "nan"], "argument --eval-box: must be a finite number"),
    (["run", "{run}", "--out", "{tmp}/x", "--ray", "--cpus-per-task", "nan"], "argument --cpus-per-task: must be a "
                                                                             "finite number"),
])
def test_numeric_options_refuse_nan_inf_and_out_of_range(run_dir, tmp_path, capsys, argv, message):
    try:
        rc = cli.main([a.format(run=run_dir, tmp=tmp_path) for a in argv])
    except SystemExit as e:  # refused by the parser (argparse exits 2)
        rc = e.code
    cap = capsys.readouterr()
    assert rc == 2 and message in cap.err and "Traceback" not in cap.err, cap.err
    assert not (tmp_path / "s").exists() and not (tmp_path / "a.ply").exists()


def test_simulator_refuses_nan_settings_in_the_library_too():
    from floxels_ext.evaluation.sim import simulate_sequence

    with pytest.raises(ValueError, match="range_noise must be a finite number"):
        simulate_sequence("crossing", 1, 0, small=True, range_noise=float("nan"))


def test_show_refuses_a_changed_source_with_the_same_point_count(run_dir, tmp_path, capsys):
    png = tmp_path / "f1.png"
    rc, cap = _main(["show", run_dir, "--frame", "000001", "--png", png], capsys)
    assert rc == 0 and png.is_file(), cap.err
    src = tmp_path / "in" / "000001.npy"
    p = np.load(src)
    p[0, 0] += 0.25  # the same number of points, one moved
    np.save(src, p)
    png.unlink()
    rc, cap = _main(["show", run_dir, "--frame", "000001", "--png", png], capsys)
    assert rc == 2 and "changed since the run wrote this flow" in cap.err and "000001.npy" in cap.err
    assert not png.exists()


def test_show_names_a_replaced_or_missing_source_not_a_broken_output(run_dir, tmp_path, capsys):
    # it said "<out>.npz: not a floxels flow output (expected a .npz written by 'floxels run')"
    # for an intact output whose input file was replaced (other point count) or deleted
    png = tmp_path / "f1.png"
    src = tmp_path / "in" / "000001.npy"
    np.save(src, np.load(src)[:-3])
    rc, cap = _main(["show", run_dir, "--frame", "000001", "--png", png], capsys)
    assert rc == 2 and "changed since the run wrote this flow" in cap.err and "000001.npy" in cap.err, cap.err
    assert "not a floxels flow output" not in cap.err and "Re-run floxels run" in cap.err
    src.unlink()
    rc, cap = _main(["show", run_dir, "--frame", "000001", "--png", png], capsys)
    assert rc == 2 and "cannot be read" in cap.err and "no such file" in cap.err, cap.err
    assert "not a floxels flow output" not in cap.err and not png.exists()


def test_a_stray_far_point_is_reported_with_its_cost(seq, fake, tmp_path, capsys):
    # one return 1 km away with the range crop off: the scan's distance transform grows ~10x
    d = _npy_dir(seq, tmp_path / "in", edit=lambda i, p: np.concatenate([p, [[1000.0, 0.0, 1.0]]]) if i == 2 else p)
    rc, cap = _run([d, "--out", tmp_path / "out", "--method", "fake", "--no-ego-motion", "--max-range", "none",
                    "--max-height", "none"], capsys)
    assert rc == 0, cap.err
    assert "floxels: warning: " in cap.err and "000002.npy: 1 point(s) lie far outside the rest of the scan" in cap.err
    assert "GB instead of" in cap.err and "crop them (--max-range" in cap.err
    summary = json.loads((tmp_path / "out" / "run_summary.json").read_text())
    assert summary["far_outliers"] == ["000002"]
    # the default crop removes it: no warning
    rc, cap = _run([d, "--out", tmp_path / "out2", "--method", "fake", "--no-ego-motion"], capsys)
    assert rc == 0 and "far outside" not in cap.err


def test_simulate_refuses_a_size_beyond_its_memory_limit_before_any_work(tmp_path, capsys):
    rc, cap = _main(["simulate", tmp_path / "big", "--beams", "100000"], capsys)
    assert rc == 2 and cap.err.startswith("floxels: error: 100000 beams x 2048 azimuth steps")
    assert "GB of memory" in cap.err and "--max-memory" in cap.err and "fewer --beams" in cap.err
    assert not (tmp_path / "big").exists()
    rc, cap = _main(["simulate", tmp_path / "s", "--small", "--frames", "2", "--max-memory", "0.1"], capsys)
    assert rc == 2 and "above the limit of 0.1 GB (--max-memory)" in cap.err
    rc, cap = _main(["-v", "simulate", tmp_path / "s", "--small", "--frames", "2"], capsys)
    assert rc == 0 and "estimated 0.3 GB peak memory" in cap.out, cap.out
