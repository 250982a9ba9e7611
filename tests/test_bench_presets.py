"""bench/bench_presets.py (issue 47's speed item) runs end to end on the CPU: every row, the
ratios to paper, the JSON."""

import importlib.util
import json
from pathlib import Path


def test_bench_presets_smoke(tmp_path):
    path = Path(__file__).resolve().parents[1] / "bench" / "bench_presets.py"
    spec = importlib.util.spec_from_file_location("bench_presets", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "presets.json"
    assert mod.main(["--beams", "16", "--lengths", "4", "--azimuth", "256", "--max-range", "20", "--iters", "3",
                     "--repeat", "1", "--frames", "0,-1", "--sim-cache", "", "--variant", "flat=accurate,refine_level=no",
                     "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    assert [c["case"] for c in d["cases"]] == ["sim/b16/L4/urban/s60"]
    rows = d["totals"]
    assert list(rows) == ["paper", "accurate", "flat"] and rows["paper"]["frames"] == 2
    assert rows["paper"]["wall_x_paper"] == 1.0 and rows["accurate"]["wall_s_per_frame"] > 0
    assert d["variants"]["flat"]["refine_level"] is False and d["variants"]["accurate"]["refine_level"] is True
