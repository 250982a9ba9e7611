"""``floxels run --mps`` (lidar/dataset/mps.py): when a private CUDA MPS daemon starts, what a
failure does, and the watcher that stops it. No GPU here: a fake ``nvidia-cuda-mps-control`` on
the PATH logs what it is asked, and the CUDA client (the probe) is replaced."""

import os
import subprocess
import sys
import time

import pytest

from floxels_ext import cli
from floxels_ext.errors import CLIError
from floxels_ext.lidar.dataset import mps

FAKE = """#!/bin/sh
echo "args $*" >> "$FAKE_LOG"
if [ "$1" = "-d" ]; then exit ${FAKE_RC:-0}; fi
read cmd
echo "stdin $cmd" >> "$FAKE_LOG"
if [ "$cmd" = get_server_list ] && [ -n "$FAKE_SERVERS" ]; then echo 4321; fi
exit 0
"""


@pytest.fixture
def fake(tmp_path, monkeypatch):
    """A fake control program on the PATH, its log, and this process's MPS state kept clean."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    prog = bin_dir / mps.CONTROL
    prog.write_text(FAKE)
    prog.chmod(0o755)
    log = tmp_path / "control.log"
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("FAKE_LOG", str(log))
    monkeypatch.setenv("FAKE_SERVERS", "1")
    for var in (mps.PIPE, mps.LOG):  # (restored as they were after the test)
        monkeypatch.setenv(var, "")
        monkeypatch.delenv(var)
    monkeypatch.setattr(mps, "_state", {"sharing": None})
    monkeypatch.setattr(mps, "PROBE_ARGS", [sys.executable, "-c", "pass"])
    monkeypatch.setattr(mps, "DEFAULT_PIPE", str(tmp_path / "no-default-daemon"))
    return log


def _lines(log):
    return log.read_text().splitlines() if log.exists() else []


@pytest.mark.parametrize("mode,device,engines,ray,env,init,expect", [
    ("off", "cuda", 4, False, {}, False, "none"),
    ("auto", "cpu", 4, False, {}, False, "none"),
    ("auto", None, 4, False, {}, False, "start"),
    ("auto", "cuda:1", 3, False, {}, False, "start"),
    ("auto", "cuda", 1, False, {}, False, "none"),
    ("auto", "cuda", 4, True, {}, False, "none"),
    ("auto", "cuda", 4, False, {mps.PIPE: "/tmp/theirs"}, False, "user"),
    ("on", "cuda", 4, False, {mps.PIPE: "/tmp/theirs"}, False, "user"),
    ("auto", "cuda", 4, False, {}, True, "none"),   # this process's context made outside MPS already
    ("on", "cuda", 4, False, {}, True, "start"),
])
def test_plan(fake, mode, device, engines, ray, env, init, expect):
    assert mps.mps_plan(mode, device, engines, ray, environ=env, cuda_initialized=init)[0] == expect


@pytest.mark.parametrize("device,engines,ray,words", [
    ("cpu", 4, False, "contradicts --device cpu"),
    ("cuda", 1, False, "this run has one"),
    (None, 4, True, "before 'ray start'"),
])
def test_plan_on_refuses_what_cannot_share(fake, device, engines, ray, words):
    with pytest.raises(ValueError, match=words):
        mps.mps_plan("on", device, engines, ray, environ={})


def test_plan_finds_a_daemon_in_the_default_place(fake, tmp_path, monkeypatch):
    default = tmp_path / "nvidia-mps"
    default.mkdir()
    (default / "control").write_text("")  # (the daemon's socket)
    monkeypatch.setattr(mps, "DEFAULT_PIPE", str(default))
    assert mps.mps_plan("auto", "cuda", 4, False, environ={})[0] == "user"


def test_plan_without_the_program(monkeypatch, tmp_path):
    monkeypatch.setattr(mps, "DEFAULT_PIPE", str(tmp_path / "none"))
    monkeypatch.setattr(mps.shutil, "which", lambda name: None)
    assert mps.mps_plan("auto", "cuda", 4, False, environ={})[0] == "none"
    with pytest.raises(ValueError, match="not on the PATH"):
        mps.mps_plan("on", "cuda", 4, False, environ={})


def test_start_points_the_process_at_the_daemon(fake):
    root = mps.start_private_mps(timeout=20)
    assert os.environ[mps.PIPE] == os.path.join(root, "pipe") and os.path.isdir(os.environ[mps.PIPE])
    assert os.environ[mps.LOG] == os.path.join(root, "log")
    assert mps.sharing() == "private"
    lines = _lines(fake)
    assert lines[0] == "args -d" and "stdin get_server_list" in lines
    assert "stdin quit" not in lines  # running: stopped by the watcher when this process ends
    mps.use_mps("auto", "cuda", 4, False)  # a later run of this process: the same daemon, still "private"
    assert mps.sharing() == "private" and _lines(fake) == lines


def test_daemon_that_does_not_start(fake, monkeypatch):
    monkeypatch.setenv("FAKE_RC", "1")
    with pytest.raises(mps.MpsError, match="exited 1"):
        mps.start_private_mps(timeout=20)
    assert mps.PIPE not in os.environ and mps.sharing() == "off"


def test_no_server_for_the_client_stops_the_daemon(fake, monkeypatch):
    monkeypatch.setenv("FAKE_SERVERS", "")
    with pytest.raises(mps.MpsError, match="no MPS server"):
        mps.start_private_mps(timeout=20)
    assert "stdin quit" in _lines(fake)
    assert mps.PIPE not in os.environ


def test_use_mps_auto_notes_a_failure_and_goes_on(fake, monkeypatch, capsys):
    monkeypatch.setattr(mps, "PROBE_ARGS", [sys.executable, "-c", "import sys; sys.exit(6)"])
    mps.use_mps("auto", "cuda", 4, False)
    assert "CUDA MPS did not start (a CUDA client exited 6)" in capsys.readouterr().err
    assert mps.PIPE not in os.environ and "stdin quit" in _lines(fake)


def test_use_mps_auto_is_silent_without_cuda(fake, monkeypatch, capsys):
    monkeypatch.setattr(mps, "PROBE_ARGS", [sys.executable, "-c", "import sys; sys.exit(4)"])
    mps.use_mps("auto", None, 3, False)
    assert capsys.readouterr().err == "" and mps.PIPE not in os.environ


def test_use_mps_on_failure_is_an_error(fake, monkeypatch):
    monkeypatch.setattr(mps, "PROBE_ARGS", [sys.executable, "-c", "import sys; sys.exit(6)"])
    with pytest.raises(CLIError, match="--mps on: CUDA MPS did not start"):
        mps.use_mps("on", "cuda", 4, False)


@pytest.mark.parametrize("mode", ["auto", "on", "off"])
def test_use_mps_keeps_the_users_daemon(fake, monkeypatch, mode):
    monkeypatch.setenv(mps.PIPE, "/tmp/their-mps")
    mps.use_mps(mode, "cuda", 4, False)
    assert mps.sharing() == "user" and _lines(fake) == []  # nothing started; "off" cannot undo theirs


def test_off_without_mps_says_off(fake):
    mps.use_mps("off", "cuda", 4, False)
    assert mps.sharing() == "off" and _lines(fake) == []


def test_a_process_without_use_mps_sees_the_users_daemon(fake, tmp_path, monkeypatch):
    """(a Ray worker: no --mps of its own; the node's daemon in the default place serves it)"""
    assert mps.sharing() == "off"
    (tmp_path / "nvidia-mps").mkdir()
    (tmp_path / "nvidia-mps" / "control").write_text("")
    monkeypatch.setattr(mps, "DEFAULT_PIPE", str(tmp_path / "nvidia-mps"))
    assert mps.sharing() == "user"


def test_watcher_stops_the_daemon_after_the_process(fake, tmp_path):
    root = tmp_path / "mpsroot"
    (root / "pipe").mkdir(parents=True)
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(0.5)"])
    w = subprocess.Popen(["sh", "-c", mps._WATCH, "w", str(proc.pid), mps.shutil.which(mps.CONTROL), str(root)])
    time.sleep(0.2)
    assert "stdin quit" not in _lines(fake)  # the process still runs
    proc.wait()
    assert w.wait(timeout=20) == 0
    assert "stdin quit" in _lines(fake) and not root.exists()


@pytest.mark.parametrize("extra,words", [
    (["--mps", "on", "--device", "cpu"], "contradicts --device cpu"),
    (["--mps", "on", "--engines", "1", "--device", "cuda"], "this run has one"),
    (["--mps", "on", "--worker-kind", "process", "--device", "cuda"], "--worker-kind process"),
    (["--mps", "on", "--ray"], "before 'ray start'"),
])
def test_cli_refuses(fake, tmp_path, capsys, extra, words):
    frames = tmp_path / "frames"
    frames.mkdir()
    assert cli.main(["run", str(frames), "--out", str(tmp_path / "out"), *extra]) == 2
    err = capsys.readouterr().err
    assert "floxels: error:" in err and words in err and "Traceback" not in err
    assert _lines(fake) == []


def test_mps_is_no_task_option():
    from argparse import Namespace

    from floxels_ext.lidar.dataset.tasks import common_options

    assert "mps" not in common_options(Namespace(mps="on", preset="paper"))


@pytest.mark.cuda
def test_engines_through_mps_give_the_same_arrays(tmp_path):
    """On a GPU with MPS (the driver's control program on the PATH): two engines through a
    private MPS daemon write the arrays of two engines taking turns, and the summary says how
    they shared the GPU. Runs as fresh processes: the daemon must come before CUDA is used."""
    import shutil

    import numpy as np

    from floxels_ext.evaluation.sim import simulate_sequence
    from floxels_ext.evaluation.seqio import save_sequence

    if shutil.which(mps.CONTROL) is None:
        pytest.skip(f"{mps.CONTROL} not on the PATH")
    save_sequence(tmp_path / "seq", simulate_sequence("urban", 16, 7, beams=32, azimuth_steps=720))
    env = {k: v for k, v in os.environ.items() if k not in (mps.PIPE, mps.LOG)}
    sharing = {}
    for mode in ("off", "on"):
        out = tmp_path / mode
        subprocess.run([sys.executable, "-m", "floxels_ext.cli", "run", str(tmp_path / "seq"), "--out", str(out),
                        "--device", "cuda", "--engines", "2", "--task-frames", "8", "--chunk", "8", "-q",
                        "--mps", mode], env=env, check=True, timeout=300)
        import json

        sharing[mode] = json.loads((out / "run_summary.json").read_text()).get("mps")
    assert sharing == {"off": "off", "on": "private"}
    files = sorted(p.name for p in (tmp_path / "off").glob("*.npz"))
    assert len(files) == 16
    for name in files:
        a, b = np.load(tmp_path / "off" / name), np.load(tmp_path / "on" / name)
        for k in ("flow", "mask", "dynamic", "evidence", "explained"):
            assert a[k].tobytes() == b[k].tobytes(), (name, k)
