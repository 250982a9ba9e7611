"""``floxels run DATASET``: every sequence through one pipeline (``lidar/dataset/stream.py``).

One call of the method serves the whole dataset; windows never leave their sequence (results equal
the plain run's, also for Floxels itself, whose batches cross sequence ends); the next sequence is
opened and read while the current one is estimated; an error of the method fails only the frames it
held, the rest are written and a re-run writes only those; one progress bar counts frames and
sequences; -q prints only the final summary."""

import json
import time
from pathlib import Path

import numpy as np
import pytest

from floxels_ext import cli
from floxels_ext.evaluation.seqio import save_sequence

FLAGS = ["--device", "cpu", "--scans", "3", "--chunk", "3"]
SIZES = (5, 4, 6)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from floxels_ext.evaluation.sim import simulate_sequence

    root = tmp_path_factory.mktemp("stream")
    for k, (scene, n) in enumerate(zip(("urban", "crossing", "highway"), SIZES)):
        save_sequence(root / f"s{k}", simulate_sequence(scene, n, k, beams=16, azimuth_steps=360))
    return root


class Spy:
    """A stream method: flow = 0.01 x world position; records its calls, the segments of the
    targets and what the pipeline had opened when each target came; can fail at one target."""

    def __init__(self, fail_at=None):
        self.calls, self.seen, self.fail_at = 0, [], fail_at
        self.jobs_open_at: dict = {}

    def stream(self, scans, targets, device, options, callback):
        self.calls += 1
        for g, seg in targets:
            assert seg.lo <= g < seg.hi
            self.seen.append((g, seg.lo, seg.hi))
            if self.fail_at is not None and len(self.seen) == self.fail_at:
                raise RuntimeError("CUDA out of memory (test)")
            scan = scans[g]
            for _ in range(200):  # the next sequence is being opened: give its thread the time it takes
                if scans.layout.source.ready() or scans.layout.exhausted:
                    break
                time.sleep(0.01)
            scans[g]  # (asking again lets the read-ahead take it in)
            jobs = scans.layout.jobs
            self.jobs_open_at[g] = (len(jobs), len(jobs) > 1 and bool(jobs[1].loader.futures or jobs[1].loader.done))
            callback(g, np.asarray(scan, np.float32) * 0.01)

    def sequence(self, scans, frames, device, options, callback):
        for f in frames:
            callback(f, np.asarray(scans[f], np.float32) * 0.01)


@pytest.fixture
def spy(monkeypatch):
    from floxels_ext import methods

    s = Spy()
    monkeypatch.setitem(methods._REGISTRY, "spy", methods.Method("spy", "test double", s.sequence,
                                                                 estimate_stream=s.stream))
    monkeypatch.setitem(methods._REGISTRY, "plainspy", methods.Method("plainspy", "test double", s.sequence))
    return s


def _outputs(out: Path) -> list[str]:
    return sorted(p.relative_to(out).as_posix() for p in out.rglob("*.npz"))


def _same(a: Path, b: Path):
    assert _outputs(a) == _outputs(b) and _outputs(a)
    for rel in _outputs(a):
        with np.load(a / rel) as x, np.load(b / rel) as y:
            assert np.array_equal(x["mask"], y["mask"]), rel
            np.testing.assert_array_equal(x["flow"], y["flow"], err_msg=rel)


def test_one_call_for_the_dataset_equals_plain_runs(data, tmp_path, spy, capsys):
    out = tmp_path / "ds"
    assert cli.main(["run", str(data), "--out", str(out), "--method", "spy", *FLAGS]) == 0
    assert spy.calls == 1                                   # one pipeline: the method never drains
    assert len(spy.seen) == sum(SIZES)
    # segments are the plain run's chunks (3 targets + their support scans), never across sequences
    assert all(hi - lo <= 3 + 2 * 2 for _, lo, hi in spy.seen)
    # the next sequence was opened, and its frames were being read, while the first one was estimated
    last_of_s0 = spy.seen[SIZES[0] - 1][0]
    opened, reading = spy.jobs_open_at[last_of_s0]
    assert opened >= 2 and reading
    for k in range(3):  # each sequence equals its plain run (same windows, same anchors)
        plain = tmp_path / f"plain{k}"
        assert cli.main(["run", str(data / f"s{k}"), "--out", str(plain), "--method", "spy", *FLAGS]) == 0
        _same(out / f"s{k}", plain)
        # one summary writer: the same keys, point classes and outliers as the plain run's
        ds_sum, plain_sum = (json.loads((d / "run_summary.json").read_text()) for d in (out / f"s{k}", plain))
        assert sorted(ds_sum) == sorted(plain_sum) and ds_sum["point_classes"]
        for key in ("point_classes", "outliers", "written", "failed", "selected", "settings"):
            assert ds_sum[key] == plain_sum[key], key
    err = capsys.readouterr().err
    assert "15/15 frames (100%)" in err and "frames/s" in err and "ETA" in err and "0 skipped, 0 failed" in err
    assert "dataset done: 3 sequences (3 done, 0 skipped, 0 failed), 15 frame(s) written" in err


def test_method_without_stream_runs_per_segment(data, tmp_path, spy):
    a, b = tmp_path / "a", tmp_path / "b"
    assert cli.main(["run", str(data), "--out", str(a), "--method", "spy", *FLAGS]) == 0
    assert cli.main(["run", str(data), "--out", str(b), "--method", "plainspy", *FLAGS]) == 0
    for rel in _outputs(a):
        with np.load(a / rel) as x, np.load(b / rel) as y:
            np.testing.assert_array_equal(x["flow"], y["flow"])


def test_method_error_fails_only_its_frames_then_rerun(data, tmp_path, spy, capsys):
    out = tmp_path / "ds"
    spy.fail_at = 7  # the 7th target (2nd of sequence s1): the stream goes on after it
    assert cli.main(["run", str(data), "--out", str(out), "--method", "spy", *FLAGS]) == 1
    err = capsys.readouterr().err
    assert "CUDA out of memory (test)" in err and "1 failure(s)" in err and "1 failed" in err, err
    assert spy.calls == 2
    assert len(_outputs(out)) == sum(SIZES) - 1
    spy.fail_at = None
    assert cli.main(["run", str(data), "--out", str(out), "--method", "spy", *FLAGS]) == 0
    err = capsys.readouterr().err
    assert f"{sum(SIZES) - 1} already done" in err and "2 skipped" in err
    assert len(_outputs(out)) == sum(SIZES)


def test_quiet_prints_only_the_summary(data, tmp_path, spy, capsys):
    assert cli.main(["-q", "run", str(data), "--out", str(tmp_path / "q"), "--method", "spy", *FLAGS]) == 0
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dataset done: 3 sequences (3 done, 0 skipped, 0 failed)"), lines


def test_floxels_stream_equals_per_sequence():
    """estimate_stream over segments laid end to end, in batches that cross segment ends, equals
    estimate_sequence over each segment alone."""
    from floxels_ext import FloxelsConfig, estimate_sequence
    from floxels_ext.estimator.windows import Segment, estimate_stream
    from floxels_ext.evaluation.sim import simulate_sequence

    cfg = FloxelsConfig(num_scans=3, max_iters=8)
    seqs = [[f.points.astype(np.float32) for f in simulate_sequence(s, n, k, beams=16, azimuth_steps=360).frames]
            for k, (s, n) in enumerate((("urban", 4), ("crossing", 3)))]
    stream = seqs[0] + seqs[1]
    segs = [Segment(0, 4), Segment(4, 7)]
    targets = [(g, segs[0]) for g in range(4)] + [(g, segs[1]) for g in range(4, 7)]
    got: dict = {}
    estimate_stream(stream, iter(targets), cfg, device="cpu", batch_size=3,
                    callback=lambda g, r: got.__setitem__(g, r.flow))
    ref = estimate_sequence(seqs[0], cfg, device="cpu") + estimate_sequence(seqs[1], cfg, device="cpu")
    assert sorted(got) == list(range(7))
    for g in range(7):
        np.testing.assert_allclose(got[g], ref[g], atol=1e-6)


def test_unreadable_neighbour_outside_frames_fails_the_run(data, tmp_path, monkeypatch, capsys):
    """A support scan outside --frames that cannot be read fails the run (exit 1, named once in
    the summary), as one sequence and as a dataset's task alike; its neighbours are written."""
    import shutil

    from floxels_ext import methods

    def windows(scans, frames, device, options, callback):  # reads each target's window of 3
        for f in frames:
            _ = scans[max(0, f - 1):f + 2]
            callback(f, np.asarray(scans[f], np.float32) * 0.01)

    monkeypatch.setitem(methods._REGISTRY, "windows", methods.Method("windows", "test double", windows))
    root = tmp_path / "root"
    shutil.copytree(data / "s0", root / "s0")
    (root / "s0" / "000001.npz").write_bytes(b"not a zip")
    args = ["--method", "windows", *FLAGS, "--frames", "2:4"]
    for inp, out in ((root / "s0", tmp_path / "plain"), (root, tmp_path / "ds")):
        assert cli.main(["run", str(inp), "--out", str(out), *args]) == 1
        summary_dir = out if inp.name == "s0" else out / "s0"
        summary = json.loads((summary_dir / "run_summary.json").read_text())
        assert [f["frame"] for f in summary["failures"]] == ["000001"] and summary["written"] == 2, summary
        assert sorted(p.name for p in summary_dir.glob("*.npz")) == ["000002.npz", "000003.npz"]
    assert "000001.npz" in capsys.readouterr().err
