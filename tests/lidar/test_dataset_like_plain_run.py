"""``floxels run DATASET`` applies to each sequence what ``floxels run SEQ`` applies to one
(issue 32): the preprocessing options (--outlier-below/--outlier-above included) and, on the CPU,
the default of torch's threads (floxels_ext.cpu_threads)."""

from pathlib import Path

import numpy as np
import pytest

from floxels_ext import cli
from floxels_ext.evaluation.seqio import save_sequence

FLAGS = ["--device", "cpu", "--scans", "3", "--method", "scaled"]


def _scaled(scans, frames, device, options, callback):
    for f in frames:
        callback(f, np.asarray(scans[f], np.float32) * 0.01)


@pytest.fixture
def scaled(monkeypatch):
    """A fast stand-in method: flow = 0.01 x world position."""
    from floxels_ext import methods

    monkeypatch.setitem(methods._REGISTRY, "scaled", methods.Method("scaled", "test double", _scaled))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from floxels_ext.evaluation.sim import simulate_sequence

    root = tmp_path_factory.mktemp("dataset")
    for k, n in enumerate((4, 3)):
        save_sequence(root / f"s{k}", simulate_sequence("crossing", n, k, beams=16, azimuth_steps=360))
    return root


def _masks(out: Path) -> dict:
    got = {}
    for p in sorted(out.rglob("*.npz")):
        with np.load(p) as z:
            got[p.relative_to(out).as_posix()] = z["mask"].copy()
    return got


def test_outlier_options_apply_to_a_dataset(data, tmp_path, scaled):
    low = ["--outlier-above", "1.5"]  # points more than 1.5 m above the sensor become outliers
    assert cli.main(["run", str(data), "--out", str(tmp_path / "default"), *FLAGS]) == 0
    assert cli.main(["run", str(data), "--out", str(tmp_path / "ds"), *FLAGS, *low]) == 0
    assert cli.main(["run", str(data / "s0"), "--out", str(tmp_path / "plain"), *FLAGS, *low]) == 0
    default, ds, plain = (_masks(tmp_path / d) for d in ("default", "ds", "plain"))
    assert any(not np.array_equal(default[k], ds[k]) for k in ds)  # the option changes the masks
    for name, m in plain.items():
        np.testing.assert_array_equal(ds[f"s0/{name}"], m, err_msg=name)


def test_cpu_thread_default_applies_to_a_dataset(data, tmp_path, scaled, monkeypatch, capsys):
    import argparse

    import floxels_ext.cpu_threads as cpu_threads
    from floxels_ext.lidar.pipeline.run_args import apply_cpu_default

    calls = []
    monkeypatch.setattr(cpu_threads, "apply_cpu_threads", lambda report=None: calls.append(report))
    assert cli.main(["run", str(data / "s0"), "--out", str(tmp_path / "plain"), *FLAGS]) == 0
    assert calls == [None]                      # the plain run: once, silent without -v
    assert cli.main(["-v", "run", str(data), "--out", str(tmp_path / "ds"), *FLAGS]) == 0
    assert len(calls) == 2 and callable(calls[1])  # the dataset: once for the job, said with -v
    # a Ray worker keeps the threads it set to its CPUs (cpu_limit); a GPU run leaves them alone
    apply_cpu_default(argparse.Namespace(cpu_limit=2), "cpu")
    apply_cpu_default(argparse.Namespace(), "cuda")
    assert len(calls) == 2
