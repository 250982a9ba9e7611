"""Issue 17, API / readers / config / demo / show part: what a new user's mistakes produce.

Each test asserts the exact behaviour: the error type and the words that name the problem,
or the documented result (times=, flow_unit=, negative frame indices, ...)."""

from __future__ import annotations

import dataclasses
import importlib
import typing
import warnings

import numpy as np
import pytest
import torch

import floxels_ext
from floxels_ext import Floxels, FloxelsConfig, cli, estimate_flow, estimate_sequence
from floxels_ext.estimator.config import parse_option_value
from floxels_ext.estimator.config_fields import check_field_types
from floxels_ext.lidar.io import LidarFormatError, MissingDependencyError, read_points
from floxels_ext.ops.grid import GridTooLargeError
from floxels_ext.estimator.scans import prepare_scans

FAST = FloxelsConfig(max_iters=40, patience=40)


def _scene(rng, n_static=150, n_car=200):
    """Static boxes and a car; returns (static points, car points)."""
    static = np.concatenate([c + rng.uniform(-1, 1, (n_static, 3)) * [2, 1, 0.8]
                             for c in ([-8, -6, 0.0], [8, -6, 0], [-8, 6, 0], [8, 6, 0])])
    car = rng.uniform(-1, 1, (n_car, 3)) * [2, 1, 0.8]
    return static, car


def _scans_at(times, v=(1.0, 0.5, 0.0), seed=0):
    """Scans at ``times`` (s) of a car moving ``v`` metres per 0.1 s among static boxes."""
    rng = np.random.default_rng(seed)
    static, car = _scene(rng)
    return [np.concatenate([static, car + np.array(v) * t / 0.1]).astype(np.float32) for t in times], len(static)


def _run(argv, capsys):
    rc = cli.main(argv)
    out = capsys.readouterr()
    return rc, out.out, out.err


# ----------------------------------------------------------------------------- config (item 4)
@pytest.mark.parametrize("field,value,words", [
    ("cluster_loss", "no", "a bool"),
    ("flow_norm_loss", 1, "a bool"),
    ("voxel_size", True, "a number"),
    ("max_iters", 2.0, "an integer"),
    ("max_iters", True, "an integer"),
    ("lr", float("nan"), "NaN"),
    ("adam_betas", (0.9,), "a tuple of 2"),
    ("adam_betas", 0.9, "a tuple of 2"),
    ("reg_scale", 2, "a string"),
])
def test_config_field_types_are_checked(field, value, words):
    with pytest.raises(TypeError, match=f"FloxelsConfig.{field} must be .*{words}|{words}") as e:
        FloxelsConfig(**{field: value})
    assert field in str(e.value)
    assert isinstance(e.value, ValueError)  # callers catching ValueError for bad settings catch it too


def test_config_normalises_compatible_values():
    cfg = FloxelsConfig(adam_betas=[0.8, 0.9], max_iters=np.int64(7), voxel_size=1, cluster_loss=np.bool_(False))
    assert cfg.adam_betas == (0.8, 0.9) and type(cfg.max_iters) is int and cfg.cluster_loss is False
    hash(cfg)  # still hashable (the list became a tuple)


def test_type_checks_are_generic_for_fields_added_later():
    @dataclasses.dataclass(frozen=True)
    class Later:
        schedule: typing.Literal["constant", "cosine"] = "constant"
        warmup: float | None = None
        flag: bool = False
        sizes: tuple[int, ...] = (1, 2)

        def __post_init__(self):
            check_field_types(self)

    Later(schedule="cosine", warmup=0.5, sizes=[3])
    for kw, words in ((dict(schedule="linear"), "'constant' or 'cosine'"), (dict(warmup="0.5"), "a number or None"),
                      (dict(flag="yes"), "a bool"), (dict(sizes=(1, 2.5)), "a tuple of an integer")):
        with pytest.raises(TypeError, match=words):
            Later(**kw)
    assert parse_option_value("schedule", "cosine", cls=Later) == "cosine"
    assert parse_option_value("warmup", "none", cls=Later) is None
    assert parse_option_value("sizes", "4,5,6", cls=Later) == (4, 5, 6)


@pytest.mark.parametrize("text,value", [("yes", True), ("no", False), ("TRUE", True), ("false", False),
                                        ("on", True), ("Off", False), ("1", True), ("0", False)])
def test_parse_bool_spellings(text, value):
    assert parse_option_value("cluster_loss", text) is value
    assert FloxelsConfig.from_strings({"cluster_loss": text}).cluster_loss is value


def test_parse_option_values_and_errors():
    assert parse_option_value("adam_betas", "0.8,0.99") == (0.8, 0.99)
    assert parse_option_value("adam_betas", "[0.8, 0.99]") == (0.8, 0.99)
    assert parse_option_value("max_iters", "1e3") == 1000
    assert parse_option_value("voxel_size", "0.3") == 0.3
    assert parse_option_value("reg_scale", "paper") == "paper"
    with pytest.raises(ValueError, match=r"option cluster_loss='maybe': expected a bool .*yes/no"):
        parse_option_value("cluster_loss", "maybe")
    with pytest.raises(ValueError, match=r"option max_iters='2.5': expected an integer"):
        parse_option_value("max_iters", "2.5")
    with pytest.raises(ValueError, match=r"no option 'clusterloss'; known: .*cluster_loss"):
        FloxelsConfig.from_strings({"clusterloss": "no"})
    with pytest.raises(ValueError, match="adam_betas"):
        FloxelsConfig.from_strings({"adam_betas": "0.9"})
    base = FloxelsConfig(max_iters=9)
    assert FloxelsConfig.from_strings({"lr": "0.1"}, base=base) == base.replace(lr=0.1)


# ----------------------------------------------------------------------------- scans / estimator (item 11)
def test_target_out_of_range_reports_the_given_index():
    scans, _ = _scans_at([0, 0.1, 0.2])
    with pytest.raises(IndexError, match=r"target index -4 is out of range for 3 scans \(valid: -3 \.\. 2\)"):
        estimate_flow(scans, target=-4)


def test_none_among_scans_is_named():
    scans, _ = _scans_at([0, 0.1, 0.2])
    with pytest.raises(TypeError, match="scan 1 must be a numpy array or torch tensor of shape \\(N, 3\\), got NoneType"):
        estimate_flow([scans[0], None, scans[2]])


def test_fit_many_needs_pairs():
    scans, _ = _scans_at([0, 0.1, 0.2])
    with pytest.raises(TypeError, match=r"windows\[0\] must be a \(scans, target\) pair"):
        Floxels(FAST).fit_many([scans])
    with pytest.raises(ValueError, match="at least one"):
        Floxels(FAST).fit_many([])


def test_sequence_refuses_a_single_scan():
    scans, _ = _scans_at([0, 0.1, 0.2])
    with pytest.raises(TypeError, match=r"not a single \(800, 3\) array"):
        estimate_sequence(scans[0], FAST)


def test_sequence_accepts_negative_frames():
    scans, _ = _scans_at([0, 0.1, 0.2, 0.3])
    cfg = FAST.replace(num_scans=3)
    a = estimate_sequence(scans, cfg, frames=[-1])
    b = estimate_sequence(scans, cfg, frames=[3])
    np.testing.assert_array_equal(a[0], b[0])
    with pytest.raises(IndexError, match=r"frame -5 is out of range for 4 scans"):
        estimate_sequence(scans, cfg, frames=[-5])
    with pytest.raises(TypeError, match="integer indices"):
        estimate_sequence(scans, cfg, frames=[1.5])


def test_a_dict_of_scans_is_refused_by_name():
    # list(dict) is its keys: it said "scan 0 must be a numpy array or torch tensor ..., got int"
    scans, _ = _scans_at([0, 0.1, 0.2])
    d = dict(enumerate(scans))
    for call in (lambda: estimate_flow(d, config=FAST), lambda: estimate_sequence(d, FAST),
                 lambda: Floxels(FAST).fit(d)):
        with pytest.raises(TypeError, match=r"scans must be a sequence \(list or tuple\).*got dict .pass list\(d"):
            call()


def test_sequence_refuses_a_bare_frame_index_and_a_callback_that_is_no_function(monkeypatch):
    # frames=2 was "'int' object is not iterable"; callback=5 failed only after the first frame's work
    import floxels_ext.estimator.api as api

    monkeypatch.setattr(api, "window_for", lambda *a: pytest.fail("work started"))
    scans, _ = _scans_at([0, 0.1, 0.2])
    with pytest.raises(TypeError, match=r"frames must be a sequence of integer indices \(e\.g\. \[2\]\), got int"):
        estimate_sequence(scans, FAST, frames=2)
    with pytest.raises(TypeError, match="callback must be a function callback.frame, result., got int"):
        estimate_sequence(scans, FAST, callback=5)


def test_nan_warning_points_at_the_callers_line():
    scans, _ = _scans_at([0, 0.1, 0.2])
    scans[1] = scans[1].copy()
    scans[1][:3] = np.nan
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        flow = estimate_flow(scans, config=FAST)
    msgs = [x for x in w if "NaN/inf" in str(x.message)]
    assert msgs and msgs[0].filename == __file__, msgs[0].filename
    assert "dropping 3 point(s)" in str(msgs[0].message) and np.isnan(flow[:3]).all()


def test_grid_too_large_names_the_config_field():
    scans, _ = _scans_at([0, 0.1, 0.2])
    with pytest.raises(GridTooLargeError, match="max_dt_cells"):
        estimate_flow(scans, config=FAST.replace(max_dt_cells=1000))


def test_bad_device_is_a_clear_error():
    scans, _ = _scans_at([0, 0.1, 0.2])
    with pytest.raises(ValueError, match="unknown device 'moon'"):
        estimate_flow(scans, device="moon")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA device is available"):
            estimate_flow(scans, device="cuda")


# ----------------------------------------------------------------------------- times= / flow_unit=
def test_equal_spacing_with_times_equals_without_times_exactly():
    times = [0.0, 0.1, 0.2, 0.3, 0.4]  # (0.3 - 0.2) / 0.1 is not exactly 1 in floats: snapped
    scans, _ = _scans_at(times)
    a = estimate_flow(scans, 2, FAST, times=times)
    b = estimate_flow(scans, 2, FAST)
    np.testing.assert_array_equal(a, b)
    sa = estimate_sequence(scans, FAST.replace(num_scans=3), frames=[0, 4], times=[100 + t for t in times])
    sb = estimate_sequence(scans, FAST.replace(num_scans=3), frames=[0, 4])
    for x, y in zip(sa, sb):
        np.testing.assert_array_equal(x, y)


def test_dropped_frame_gives_the_right_offsets_and_flow():
    times = [0.0, 0.1, 0.3, 0.4]  # the scan at 0.2 s was dropped
    scans, n_static = _scans_at(times)
    prep = prepare_scans(scans, 1, "cpu", times=times)
    assert prep.offsets == [-1.0, 2.0, 3.0]
    prep = prepare_scans(scans, 1, "cpu", times=times, period=0.2)
    assert prep.offsets == pytest.approx([-0.5, 1.0, 1.5])
    cfg = FloxelsConfig(max_iters=150)
    flow = estimate_flow(scans, 1, cfg, times=times)
    np.testing.assert_allclose(np.median(flow[n_static:], 0), [1.0, 0.5, 0.0], atol=0.05)
    assert np.abs(flow[:n_static]).max() < 0.05
    # non-integer offsets reach the solver: a period of 0.2 s doubles the flow per period
    flow2 = estimate_flow(scans, 1, cfg, times=times, frame_period=0.2)
    np.testing.assert_allclose(np.median(flow2[n_static:], 0), [2.0, 1.0, 0.0], atol=0.1)
    ms = estimate_flow(scans, 1, cfg, times=times, flow_unit="m/s")
    np.testing.assert_allclose(ms, flow / 0.1, rtol=1e-5, atol=1e-5)
    # per-frame flows of a sequence with a gap: same unit as the others
    seq = estimate_sequence(scans, cfg.replace(num_scans=3), frames=[1, 2], times=times)
    for f in seq:
        np.testing.assert_allclose(np.median(f[n_static:], 0), [1.0, 0.5, 0.0], atol=0.08)


@pytest.mark.parametrize("kw,err,words", [
    (dict(times=[0, 0.1]), ValueError, "times has 2 entries but there are 3 scans"),
    (dict(times=[0, 0.2, 0.1]), ValueError, "strictly increasing"),
    (dict(times=[0, 0.1, 0.1]), ValueError, "strictly increasing"),
    (dict(times=[0, float("nan"), 0.2]), ValueError, "finite"),
    (dict(times=[0, "a", 0.2]), TypeError, r"times\[1\] must be a number"),
    (dict(times=0.1), TypeError, "times must be a sequence"),
    (dict(flow_unit="km/h"), ValueError, "flow_unit must be 'frame' or 'm/s'"),
    (dict(flow_unit="m/s"), ValueError, "needs the scans' times="),
    (dict(times=[0, 0.1, 0.2], frame_period=0), ValueError, "frame_period must be a positive"),
    (dict(frame_period="0.1", flow_unit="m/s"), TypeError, "frame_period must be a number"),
])
def test_times_errors(kw, err, words):
    scans, _ = _scans_at([0, 0.1, 0.2])
    with pytest.raises(err, match=words):
        estimate_flow(scans, config=FAST, **kw)


def test_frame_period_gives_m_per_s_without_times():
    scans, _ = _scans_at([0, 0.1, 0.2])
    a = estimate_flow(scans, config=FAST)
    b = estimate_flow(scans, config=FAST, frame_period=0.1, flow_unit="m/s")
    np.testing.assert_allclose(b, a * 10, rtol=1e-6)


def test_time_weight_accepts_real_offsets():
    cfg = FloxelsConfig()
    assert cfg.time_weight(0.5) == pytest.approx(4.0) and cfg.time_weight(-1.5) == pytest.approx(1 / 2.25)


def test_methods_take_times():
    from floxels_ext import methods
    from floxels_ext.baselines.registry import run_sequence

    times = [0.0, 0.1, 0.3, 0.4]
    scans, n_static = _scans_at(times)
    got = {}
    methods.get_method("floxels").estimate_sequence(scans, [1], "cpu", {"num_scans": 3, "max_iters": 100},
                                                    lambda f, flow: got.setdefault(f, flow), times=times)
    np.testing.assert_allclose(np.median(got[1][n_static:], 0), [1.0, 0.5, 0.0], atol=0.08)

    class Fit:  # a two-scan method whose "flow" is the displacement to the other scan's time
        def __init__(self, src, dst, cfg, device):
            self.flow = np.full((len(src), 3), float(dst[0, 0] - src[0, 0]), np.float32)

    stamped = [np.full((2, 3), t, np.float32) for t in times]
    flows = run_sequence(Fit, None, stamped, None, "cpu", times=times)
    # per period (0.1 s): pairs (0,1) 0.1 s apart, (1,2) 0.2 s apart, (2,3), last (3,2) negated
    np.testing.assert_allclose([f[0, 0] for f in flows], [0.1, 0.1, 0.1, 0.1], rtol=1e-5)
    assert [f[0, 0] for f in run_sequence(Fit, None, stamped[:2], None, "cpu")] == pytest.approx([0.1, 0.1])


# ----------------------------------------------------------------------------- readers (item 3, 9)
def _ordered_scan(n=3000, cols=4):
    rng = np.random.default_rng(1)
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    cols_ = [10 * np.cos(ang), 10 * np.sin(ang), rng.normal(-1.5, 0.05, n)] + [rng.uniform(0, 1, n)] * (cols - 3)
    return np.stack(cols_, 1).astype(np.float32)


def test_transposed_npy_is_refused(tmp_path):
    np.save(tmp_path / "t.npy", _ordered_scan(1000)[:, :3].T)
    with pytest.raises(LidarFormatError, match=r"t.npy: array: shape \(3, 1000\) looks transposed.*\(1000, 3\)"):
        read_points(tmp_path / "t.npy")
    np.savez(tmp_path / "t.npz", points=_ordered_scan(1000)[:, :4].T)
    with pytest.raises(LidarFormatError, match=r"t.npz: 'points': shape \(4, 1000\) looks transposed"):
        read_points(tmp_path / "t.npz")
    np.save(tmp_path / "ok.npy", _ordered_scan(1000)[:, :3])
    assert len(read_points(tmp_path / "ok.npy")) == 1000


def test_wrong_bin_columns_is_refused(tmp_path):
    _ordered_scan(3000, 4).tofile(tmp_path / "k.bin")
    for wrong in (3, 6):
        with pytest.raises(LidarFormatError, match=f"k.bin: reading it with {wrong} columns .*use --bin-columns 4"):
            read_points(tmp_path / "k.bin", bin_columns=wrong)
    assert len(read_points(tmp_path / "k.bin", bin_columns=4)) == 3000
    assert len(read_points(tmp_path / "k.bin")) == 3000
    _ordered_scan(3001, 4).tofile(tmp_path / "odd.bin")  # 16 * 3001 bytes is not a multiple of 12
    with pytest.raises(LidarFormatError, match="odd.bin: size 48016 bytes is not a whole number of rows of 3"):
        read_points(tmp_path / "odd.bin", bin_columns=3)
    with pytest.raises(ValueError, match="bin_columns must be an integer >= 3"):
        read_points(tmp_path / "k.bin", bin_columns=2)


def test_garbage_bin_is_refused(tmp_path):
    (tmp_path / "g.bin").write_bytes(np.random.default_rng(0).bytes(16000))
    with pytest.raises(LidarFormatError, match="g.bin: .* beyond 100 km: not a float32 x y z"):
        read_points(tmp_path / "g.bin")


def test_feather_without_pyarrow(tmp_path, monkeypatch):
    real = importlib.import_module

    def fake(name, *a, **k):
        if name.startswith("pyarrow"):
            raise ImportError(f"No module named {name!r}")
        return real(name, *a, **k)

    monkeypatch.setattr(importlib, "import_module", fake)
    (tmp_path / "1.feather").write_bytes(b"ARROW1")
    with pytest.raises(MissingDependencyError, match=r"pip install 'floxels_ext\[av2\]'"):
        read_points(tmp_path / "1.feather")


# ----------------------------------------------------------------------------- CLI: demo, show, globals (item 9)
@pytest.mark.parametrize("argv,words", [
    (["demo", "--scene", "moon"], "argument --scene: invalid choice: 'moon'"),
    (["demo", "--iters", "0"], "--iters must be >= 1, got 0"),
    (["demo", "--device", "moon"], "unknown device 'moon'"),
    (["demo", "--png", "/nonexistent_dir/x.png"], "directory /nonexistent_dir does not exist"),
    (["nosuchcommand"], "invalid choice: 'nosuchcommand'"),
])
def test_demo_user_errors_exit_2(argv, words, capsys):
    try:
        rc = cli.main(argv)
    except SystemExit as e:  # argparse
        rc = e.code
    err = capsys.readouterr().err
    assert rc == 2 and "floxels: error: " in err and words in err, err


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without a GPU")
def test_demo_cuda_without_gpu(capsys):
    rc, _, err = _run(["demo", "--device", "cuda"], capsys)
    assert rc == 2 and "floxels: error: --device cuda: " in err and "no CUDA device" in err


def test_show_refuses_non_outputs(tmp_path, capsys):
    (tmp_path / "x.bin").write_bytes(b"\0" * 64)
    np.savez(tmp_path / "r.npz", a=np.zeros(3))
    (tmp_path / "z.npz").write_bytes(b"not a zip")
    np.savez(tmp_path / "s.npz", points=np.zeros((4, 3)), flow=np.zeros((5, 3)))
    for name, words in (("x.bin", "this is a .bin file"), ("r.npz", "no 'flow'"),
                        ("z.npz", "not a .npz (zip) archive"), ("s.npz", "but 'flow' has 5 rows")):
        rc, _, err = _run(["show", str(tmp_path / name), "--png", str(tmp_path / "o.png")], capsys)
        assert rc == 2 and f"floxels: error: {tmp_path / name}: not a floxels flow output" in err, err
        assert words in err, err
        assert "pickle" not in err


def test_show_draws_an_output(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    rng = np.random.default_rng(0)
    pts = rng.uniform(-20, 20, (2000, 3)).astype(np.float32)
    flow = np.zeros_like(pts)
    flow[:100] = [0.8, 0, 0]
    pts[:100] = rng.uniform(-1, 1, (100, 3)) + [5, 5, 0]
    np.savez(tmp_path / "000000.npz", points=pts, flow=flow, mask=np.ones(len(pts), bool))
    rc, out, err = _run(["show", str(tmp_path), "--png", str(tmp_path / "o.png"), "--frame-period", "0.1"], capsys)
    assert rc == 0, err
    assert (tmp_path / "o.png").read_bytes()[:4] == b"\x89PNG" and "100 moving" in out


def test_version_and_verbosity(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("floxels_ext ")
    p = cli.build_parser()
    assert p.parse_args(["simulate", "x"]).verbosity == 0
    assert p.parse_args(["-q", "simulate", "x"]).verbosity == -1
    assert p.parse_args(["simulate", "x", "--verbose"]).verbosity == 1
    assert p.parse_args(["-v", "simulate", "x"]).verbosity == 1
    with pytest.raises(SystemExit) as e:
        p.parse_args(["-q", "-v", "simulate", "x"])
    assert e.value.code == 2 and "floxels: error: argument -v/--verbose: not allowed with argument -q" in \
        capsys.readouterr().err


def test_demo_without_matplotlib_skips_the_png(tmp_path, capsys, monkeypatch):
    from floxels_ext.evaluation import demo

    real = importlib.import_module

    def fake(name, *a, **k):
        if name.startswith("matplotlib"):
            raise ImportError("No module named 'matplotlib'")
        return real(name, *a, **k)

    monkeypatch.setattr(importlib, "import_module", fake)
    args = type("A", (), dict(scene="crossing", seed=0, scans=3))()
    pts = np.zeros((5, 3), np.float32)
    demo._picture(tmp_path / "d.png", pts, pts, pts, args)
    out = capsys.readouterr().out
    assert "no picture:" in out and "pip install 'floxels_ext[viz]'" in out and not (tmp_path / "d.png").exists()


def test_floxels_version_attribute():
    assert isinstance(floxels_ext.__version__, str)
