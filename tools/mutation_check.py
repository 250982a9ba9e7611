"""Does the test suite catch a wrong Floxels? Small deliberate bugs, one at a time, in a scratch copy.

    python tools/mutation_check.py [--only NAME ...] [--json FILE] [--list]

Copies the working tree's tracked files (and the compiled ``python/floxels_ext/_C*.so``) to a
scratch directory, checks that every test subset named below passes there unchanged, then for
each mutation (a ``(file, old text, new text)`` replacement; the old text must occur exactly
once) applies it, runs that mutation's tests (a fast subset per mutation: the tests that guard the
code it changes; all of them, so the report names every test that caught it), and restores
the file. A mutation is *caught* when its
tests fail. Prints a table, writes JSON (default ``bench/results/mutation_check.json``) and
exits 1 if any mutation was missed, or if the baseline fails. Every mutation on the list must
be caught (issue 34): add tests, not exceptions.

Only Python is mutated (a C++ mutation would need a ~4-minute rebuild each); the C++/CUDA
kernels are guarded by the op tests against scipy, scikit-learn, ``grid_sample`` and the plain
loop of tests/ops/test_solver.py. Tests that read ``../shared`` (the paper, real data) skip in
the scratch copy. Set ``OMP_NUM_THREADS=1`` on a shared machine.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

PAPER = "tests/estimator/test_paper_settings.py"
E2E_ONE = "tests/estimator/test_reference_end_to_end.py::test_solver_matches_reference_over_the_whole_optimisation[crossing]"
READINGS = "tests/estimator/test_estimator.py::test_readings_match_reference_implementation"
RESUME = "tests/lidar/test_run_resume.py"
CFG = "python/floxels_ext/estimator/config.py"
REF = "python/floxels_ext/reference/estimator.py"
SOLVER = "python/floxels_ext/ops/solver.py"
STOP = "python/floxels_ext/estimator/early_stopping.py"
OUTS = "python/floxels_ext/lidar/io/outputs.py"
RES = "python/floxels_ext/lidar/pipeline/resume.py"

# (name, file, old, new, tests). The first four passed the whole suite before issue 34.
MUTATIONS = [
    ("truncation default 5 -> 50", CFG, "truncation: float = 5.0", "truncation: float = 50.0", [PAPER]),
    ("patience default 250 -> 100", CFG, "patience: int = 250", "patience: int = 100", [PAPER]),
    ("reg_scale='paper' silently ignored", CFG, 'if self.reg_scale == "support":',
     'if self.reg_scale in ("support", "paper"):', [PAPER]),
    ("resume counts an unreadable output as done", OUTS,
     "    except Exception:\n        return None\n    settings = read_settings(path)",
     "    except Exception:\n        return {\"settings\": {}, \"inputs\": None}\n    settings = read_settings(path)",
     [RESUME]),
    # paper settings
    ("lambda_C default 0.6 -> 0.06", CFG, "lambda_c: float = 0.6", "lambda_c: float = 0.06", [PAPER]),
    ("lambda_g decay 100 -> 10 iterations", CFG, "lambda_g_decay_iters: int = 100", "lambda_g_decay_iters: int = 10",
     [PAPER]),
    ("lambda_g schedule twice as slow", CFG, "a = it / self.lambda_g_decay_iters",
     "a = it / (2 * self.lambda_g_decay_iters)", [PAPER]),
    ("Adam lr default 0.05 -> 0.1", CFG, "lr: float = 0.05", "lr: float = 0.1", [PAPER]),
    ("min delta default 0.01 -> 0.001", CFG, "min_delta: float = 0.01", "min_delta: float = 0.001", [PAPER]),
    ("DBSCAN eps default 0.5 -> 1.0", CFG, "dbscan_eps: float = 0.5", "dbscan_eps: float = 1.0", [PAPER]),
    ("DBSCAN min points default 4 -> 5", CFG, "dbscan_min_samples: int = 4", "dbscan_min_samples: int = 5", [PAPER]),
    ("time weights 1/t^2 -> 1/|t|", CFG, "time_weight_power: float = 2.0", "time_weight_power: float = 1.0",
     [PAPER]),
    ("DT cell default 0.1 -> 0.2", CFG, "dt_cell: float = 0.1 ", "dt_cell: float = 0.2 ", [PAPER]),
    ("voxel default 0.5 -> 0.4", CFG, "voxel_size: float = 0.5", "voxel_size: float = 0.4", [PAPER]),
    ("default window 5 -> 3 scans", CFG, "num_scans: int = 5 ", "num_scans: int = 3 ", [PAPER]),
    ("floxels run's default window (the paper preset's) 5 -> 3", CFG, '    "paper": {},',
     '    "paper": {"num_scans": 3},', [PAPER]),
    # what the solver is told
    ("solver ignores truncation_mode='clamp'", SOLVER, '1.0 if cfg.truncation_mode == "clamp" else 0.0', "0.0",
     [PAPER]),
    ("solver ignores lr_milestones", SOLVER, "float(len(ms)),", "0.0,", [PAPER]),
    ("solver ignores cluster_loss_mean='clustered'", SOLVER, '1.0 if cfg.cluster_loss_mean == "clustered" else 0.0',
     "0.0", [PAPER]),
    ("solver lambda_g start/end swapped", SOLVER, "lg0, lg1 = (cfg.lambda_g_start, cfg.lambda_g_end)",
     "lg0, lg1 = (cfg.lambda_g_end, cfg.lambda_g_start)", [PAPER]),
    # the reference (the oracle of the end-to-end check)
    ("reference ignores truncation_mode='clamp'", REF,
     'trunc_above = cfg.truncation if cfg.truncation_mode == "clamp" else 0.0', "trunc_above = 0.0", [READINGS]),
    ("reference cluster term always over all points", REF,
     'n_c = n if cfg.cluster_loss_mean == "all" else max(int(keep.sum()), 1)', "n_c = n", [READINGS]),
    ("reference flow norm without its lambda_g schedule", REF, "scale * cfg.lambda_g(it) * norms.mean()",
     "scale * cfg.lambda_g_start * norms.mean()", [E2E_ONE]),
    ("early stopping ignores min delta", STOP, "if loss < self.ref - self.min_delta:", "if loss < self.ref:",
     ["tests/ops/test_solver.py", E2E_ONE]),
    # resume
    ("resume ignores changed settings", RES, "if diff and clash is None:", "if False:", [RESUME]),
    ("resume ignores changed inputs", RES, "why = inputs_diff(rec[\"inputs\"], json.loads(inputs[i]))", "why = None",
     [RESUME]),
    ("resume window is the frame alone", RES, "return range(min(lo, max(i - 1, 0)), max(hi, min(i + 2, n)))",
     "return range(i, i + 1)", [RESUME]),
    ("resume records no modification time", RES, "stat[j] = [int(st.st_size), int(st.st_mtime_ns)]",
     "stat[j] = [int(st.st_size), 0]", [RESUME]),
    ("resume records no poses", RES, "if poses is not None else None", "if False else None", [RESUME]),
    ("resume records no times", RES, '"times": None if times_s is None else', '"times": None if True else',
     [RESUME]),
    ("dataset sequences resume without the input check", RES,
     "args.force, inputs=inputs, report=resume_report or report)", "args.force, report=resume_report or report)",
     [RESUME]),
    ("written dataset sequences skipped unchecked", "python/floxels_ext/lidar/dataset/run.py",
     "_check_written_tasks([t for t in tasks if not t.todo], args)", "pass", [RESUME]),
    ("temporaries of other frames swept", OUTS, 'if m and (names is None or m.group("name") in names):', "if m:",
     [RESUME]),
]


def scratch_copy(dest: Path) -> None:
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, check=True, capture_output=True).stdout
    for rel in filter(None, files.decode().split("\0")):
        src = ROOT / rel
        if src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)
    libs = glob.glob(str(ROOT / "python" / "floxels_ext" / "_C*.so"))
    if not libs:
        sys.exit("no compiled extension in python/floxels_ext/ (copy or build it first)")
    for so in libs:
        shutil.copy2(so, dest / "python" / "floxels_ext")


def run_tests(root: Path, tests: list[str], timeout: float, first_failure: bool = False):
    """(pytest's exit status, seconds, its last line, the failed tests' names)."""
    env = {**os.environ, "PYTHONPATH": str(root / "python"), "PYTHONDONTWRITEBYTECODE": "1"}
    t0 = time.perf_counter()
    try:
        r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rf", "-p", "no:cacheprovider",
                            *(["-x"] if first_failure else []), *tests], cwd=root,
                           env=env, capture_output=True, text=True, timeout=timeout)
        rc, out = r.returncode, r.stdout + r.stderr
    except subprocess.TimeoutExpired:
        rc, out = -1, "timeout"
    lines = out.strip().splitlines()
    failed = [ln.split()[1].split("::", 1)[-1] for ln in lines if ln.startswith("FAILED ")]
    return rc, time.perf_counter() - t0, lines[-1] if lines else "", failed


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="+", help="run only mutations whose name contains one of these")
    ap.add_argument("--list", action="store_true", help="list the mutations and exit")
    ap.add_argument("--json", default=str(ROOT / "bench" / "results" / "mutation_check.json"))
    ap.add_argument("--timeout", type=float, default=900.0, help="s per test run")
    args = ap.parse_args()
    muts = [m for m in MUTATIONS if not args.only or any(o in m[0] for o in args.only)]
    if args.list:
        for name, path, _, _, tests in muts:
            print(f"{name:<48} {path:<44} {' '.join(tests)}")
        return 0
    rows, ok = [], True
    with tempfile.TemporaryDirectory(prefix="floxels_mutation_") as tmp:
        root = Path(tmp)
        scratch_copy(root)
        subsets = sorted({t for m in muts for t in m[4]})
        rc, secs, last, _ = run_tests(root, subsets, args.timeout, first_failure=True)
        print(f"baseline (no mutation) on {len(subsets)} test subset(s): {'pass' if rc == 0 else 'FAIL'} "
              f"in {secs:.0f} s ({last})", flush=True)
        if rc != 0:
            print("the unmutated copy must pass its tests first", file=sys.stderr)
            return 1
        for name, path, old, new, tests in muts:
            target = root / path
            text = target.read_text()
            if text.count(old) != 1:
                print(f"{name}: the text to replace occurs {text.count(old)} times in {path} (stale list)",
                      file=sys.stderr)
                ok = False
                rows.append(dict(name=name, file=path, tests=tests, caught=None, error="stale"))
                continue
            target.write_text(text.replace(old, new))
            try:
                rc, secs, last, failed = run_tests(root, tests, args.timeout)
            finally:
                target.write_text(text)
            caught = rc != 0
            ok &= caught
            rows.append(dict(name=name, file=path, tests=tests, caught=caught, seconds=round(secs, 1), pytest=last,
                             failed=failed))
            print(f"{'caught' if caught else 'MISSED':<7} {secs:6.0f} s  {name}  ({last}; {', '.join(failed)})",
                  flush=True)
    n_caught = sum(1 for r in rows if r["caught"])
    print(f"\n{n_caught} of {len(rows)} mutations caught")
    os.makedirs(os.path.dirname(args.json), exist_ok=True)
    with open(args.json, "w") as fh:
        json.dump(dict(caught=n_caught, total=len(rows), rows=rows), fh, indent=1)
    print(f"wrote {args.json}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
