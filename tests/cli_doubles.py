"""What the CLI tests of issue 45 share: a small simulated sequence, an instant method standing
in for Floxels, frames written as .npy files, and ``cli.main`` run with its stderr checked for
tracebacks."""

import numpy as np
import pytest

from floxels_ext import cli, methods

_SEQS: dict = {}


def simulated(n: int, seed: int):
    """The 16-beam 'crossing' scene, ``n`` frames (cached: the tests only read it)."""
    from floxels_ext.evaluation.sim import simulate_sequence

    if (n, seed) not in _SEQS:
        _SEQS[n, seed] = simulate_sequence("crossing", n, seed, beams=16, azimuth_steps=360)
    return _SEQS[n, seed]


def register_fake(monkeypatch, flow=(0.4, 0.0, 0.0), name: str = "fake", support_frames=None) -> list:
    """Registers method ``name`` answering ``flow`` for every point (instant, exact; reading
    the scans of ``support_frames(i, n, options)`` besides its own, when given); returns the
    list of the frame lists it was asked for."""
    calls = []

    def est(scans, frames, device, options, callback, times=None):
        calls.append(list(frames))
        for f in frames:
            callback(f, np.tile(np.float32(flow), (len(scans[f]), 1)))

    monkeypatch.setitem(methods._REGISTRY, name, methods.Method(name, "test double", est,
                                                                support_frames=support_frames))
    return calls


@pytest.fixture
def fake(monkeypatch):
    """The instant method as ``--method fake`` (import this fixture into a test module)."""
    return register_fake(monkeypatch)


def npy_frames(seq, d, n=None, name="{i:06d}"):
    """The frames' world points as float32 .npy files in ``d`` (read with --no-ego-motion)."""
    d.mkdir(parents=True, exist_ok=True)
    for i, fr in enumerate(seq.frames[:n]):
        np.save(d / f"{name.format(i=i)}.npy", fr.points.astype(np.float32))
    return d


def main(argv, capsys):
    """``cli.main(argv)`` -> (exit status, captured output); never a traceback."""
    rc = cli.main([str(a) for a in argv])
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err
    return rc, cap
