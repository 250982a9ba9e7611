"""What the export formats read of a run (``lidar/export/run_frames.py``): the next frame and the
time to it from each output's inputs record, the frame period, and the flow as a displacement to
the next frame in its coordinates, scaled from the frame period to the actual interval."""

import json

import numpy as np

from floxels_ext.lidar.export.run_frames import displacement_to_next, find_sequences, sequence_infos
from floxels_ext.lidar.io.outputs import write_output


def _output(path, name, times, n=3):
    """A minimal output of a run whose window names ``times`` (name -> seconds after ``name``)."""
    rec = {"scans": {k: [1, 1] for k in times}, "poses": None, "times": times}
    write_output(path / f"{name}.npz", flow=np.zeros((n, 3), np.float32), mask=np.ones(n, bool),
                 settings=np.str_(json.dumps({"ego_motion": "table"})), inputs=np.str_(json.dumps(rec)),
                 ego_motion=np.eye(4))


def test_steps_period_and_next_frames(tmp_path):
    # sweeps at 0, 100.2 ms, 199.9 ms, 300.0 ms; every window holds its neighbours
    t = {"a1": 0.0, "a2": 0.1002, "a3": 0.1999, "a10": 0.3}  # natural order: a1 a2 a3 a10
    names = list(t)
    for k, name in enumerate(names):
        win = names[max(k - 1, 0):k + 2]
        _output(tmp_path, name, {w: round(t[w] - t[name], 9) for w in win})
    [seq] = find_sequences(tmp_path)
    assert [p.stem for p in seq.outputs] == names
    infos, period = sequence_infos(seq)
    assert [i.next_name for i in infos] == ["a2", "a3", "a10", None]
    np.testing.assert_allclose([i.step for i in infos[:3]], [0.1002, 0.0997, 0.1001], atol=1e-12)
    assert infos[3].step is None
    assert period == np.median([0.1002, 0.0997, 0.1001])


def test_displacement_to_next():
    rng = np.random.default_rng(0)
    p, f = rng.normal(size=(5, 3)) * 20, rng.normal(size=(5, 3))
    c, s = np.cos(0.3), np.sin(0.3)
    E = np.array([[c, -s, 0, 1.5], [s, c, 0, -0.5], [0, 0, 1, 0.1], [0, 0, 0, 1.0]])
    d = displacement_to_next(p, f, E, 1.002)
    np.testing.assert_allclose(d, (E[:3, :3] @ (p + 1.002 * f).T).T + E[:3, 3] - p, atol=1e-12)
    np.testing.assert_allclose(displacement_to_next(p, f, None, 0.5), 0.5 * f, atol=1e-12)
