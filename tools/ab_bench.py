"""The regression guard: two (or more) commits built side by side on one GPU host, their speed
benches interleaved, each figure's ratio printed (issue 42: a 2x frame regression landed unseen).

Run ``prepare`` here (it needs git), then ``run`` in one device call:

    python tools/ab_bench.py prepare 37d68ff HEAD          # sources into .ab/<name>/ (ignored by git)
    python tools/ab_bench.py prepare 37d68ff WORKTREE      # the working tree as it is, uncommitted changes too
    # device call, carrying .ab:  python3 tools/ab_bench.py run --rounds 2 --out $OUT

``run`` builds every prepared source with CUDA into /tmp/ab/<name> (in parallel), then, round by
round and source by source (A, B, A, B, ...: a host's drift touches both alike), runs that
source's own ``bench/bench_speed.py --no-reference --no-cpu`` and ``bench/bench_run.py`` against
its own build, and prints one table: each figure's median over the rounds per source and its
ratio to the first source (for times, > 1 means slower; for rates, < 1), after every round (a
call that runs out of time keeps the rounds it finished). Writes ab_bench.json. With
``--benches-from-last`` every build is timed by the last source's bench scripts, so that
bench_run's ``--data DIR`` (the simulated files built once, reused by every run: ~1 min a bench
run otherwise) can be given for older commits too:

    python3 tools/ab_bench.py run --rounds 3 --benches run --benches-from-last \
        --run-args "--frames 768 --data /tmp/ab_data --no-ceiling --run-args '--preset accurate'"

Before the benches, ``--pytest ARGS`` runs the last source's tests against its build, and
``--same-flows ARGS`` runs tools/same_flows.py with every build, each compared byte for byte
with the first's (``prepare --shared`` copies ../shared/data into .ab/shared, where the
sources' tests and same_flows find the real scans). One call then holds the whole landing check:

    python tools/ab_bench.py prepare --shared 37d68ff WORKTREE
    python3 tools/ab_bench.py run --rounds 3 --alternate --benches speed \
        --pytest "-m cuda -n 8 tests" --same-flows "--scenes urban crossing --beams 32 --lengths 5 11"

Every change to the estimator or the pipeline lands with this table (bench/RESULTS.md).
"""

from __future__ import annotations

import argparse
import shlex
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
AB = ROOT / ".ab"

# (label, bench, JSON path, lower is better)
FIGURES = [
    ("frame ms (bench_speed whole frame)", "speed", ("frame_s",), True, 1e3),
    ("sequence frames/s (bench_speed, batch 16)", "speed", ("seq_fps",), False, 1.0),
    ("floxels run KITTI frames/s", "run", ("runs", "kitti", "frames_per_s"), False, 1.0),
    ("floxels run AV2 frames/s", "run", ("runs", "av2", "frames_per_s"), False, 1.0),
    # the rows of bench_run's --variant paper=... (the first run's preset being another one)
    ("floxels run KITTI frames/s, variant paper", "run", ("runs", "kitti+paper", "frames_per_s"), False, 1.0),
    ("floxels run AV2 frames/s, variant paper", "run", ("runs", "av2+paper", "frames_per_s"), False, 1.0),
    ("in-memory ceiling frames/s", "run", ("ceiling", "frames_per_s"), False, 1.0),
    # bench_run_fresh.py: a fresh process a run, its start inside the wall (as a user runs it)
    ("floxels run KITTI frames/s, fresh process", "fresh", ("runs", "kitti", "frames_per_s"), False, 1.0),
    ("floxels run AV2 frames/s, fresh process", "fresh", ("runs", "av2", "frames_per_s"), False, 1.0),
]


def prepare(revs: list[str], shared: bool = False) -> None:
    AB.mkdir(exist_ok=True)  # (.gitignore lists /.ab/)
    if shared:  # the shared real data where every source's ROOT/../shared finds it (.ab/shared)
        src = ROOT.parent / "shared" / "data"
        if not src.is_dir():
            sys.exit(f"ab_bench: error: --shared: {src} not found")
        shutil.rmtree(AB / "shared", ignore_errors=True)
        shutil.copytree(src, AB / "shared" / "data")
    names = []
    for rev in revs:
        if rev == "WORKTREE":
            name = "worktree"
            dst = AB / name
            shutil.rmtree(dst, ignore_errors=True)
            files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT, check=True,
                                   capture_output=True, text=True).stdout.split("\n")
            for f in files:
                if f and (ROOT / f).is_file() and not f.startswith(".ab/"):
                    (dst / f).parent.mkdir(parents=True, exist_ok=True)
                    shutil.copy2(ROOT / f, dst / f)
        else:
            sha = subprocess.run(["git", "rev-parse", "--short", rev], cwd=ROOT, check=True, capture_output=True,
                                 text=True).stdout.strip()
            name = f"{len(names)}_{sha}"
            dst = AB / name
            shutil.rmtree(dst, ignore_errors=True)
            dst.mkdir(parents=True)
            archive = subprocess.run(["git", "archive", "--format=tar", sha], cwd=ROOT, check=True,
                                     capture_output=True).stdout
            subprocess.run(["tar", "-x", "-C", str(dst)], input=archive, check=True)
        names.append(name)
        print(f"{rev} -> .ab/{name}")
    (AB / "order.json").write_text(json.dumps(names) + "\n")


def _build(name: str, log_dir: Path, cuda: bool) -> tuple[str, int, float]:
    t0 = time.perf_counter()
    env = dict(os.environ, FLOXELS_CUDA="ON" if cuda else "OFF",
               TORCH_CUDA_ARCH_LIST=os.environ.get("TORCH_CUDA_ARCH_LIST", "9.0"))
    with open(log_dir / f"build_{name}.log", "w") as log:
        rc = subprocess.run([sys.executable, "-m", "pip", "install", "--no-build-isolation", "--no-deps", "--target",
                             f"/tmp/ab/{name}", "--upgrade", str(AB / name)], env=env, stdout=log,
                            stderr=subprocess.STDOUT, timeout=600).returncode
    return name, rc, time.perf_counter() - t0


def _get(d: dict, path: tuple):
    for k in path:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def run(args) -> int:
    names = json.loads((AB / "order.json").read_text())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    build = [n for n in names if not (args.skip_built and (Path("/tmp/ab") / n / "floxels_ext").is_dir())]
    with ThreadPoolExecutor(max(1, len(build))) as ex:
        for name, rc, s in ex.map(lambda n: _build(n, out, args.device == "cuda"), build):
            print(f"build {name}: rc {rc} in {s:.0f} s", flush=True)
            if rc != 0:
                return 1
    failed = _checks(args, names, out)
    results: dict[str, dict[str, list]] = {n: {"speed": [], "run": [], "fresh": []} for n in names}
    benches = {"speed": ["bench/bench_speed.py", "--device", args.device, "--no-reference", "--no-cpu",
                         *shlex.split(args.speed_args)],
               "run": ["bench/bench_run.py", "--device", args.device, *shlex.split(args.run_args)],
               "fresh": ["bench/bench_run_fresh.py", "--device", args.device, *shlex.split(args.fresh_args)]}
    for rnd in range(args.rounds):
        # --alternate: A, B in odd rounds, B, A in even ones, so that neither source always runs
        # first after the other's bench (the order moved a figure by 9 % once: RESULTS, the guard)
        order = names[::-1] if args.alternate and rnd % 2 else names
        for bench in args.benches:
            for name in order:
                # --benches-from-last: every build timed by the newest source's bench scripts (options
                # an older source's scripts lack, e.g. bench_run's --data); the build is still its own
                src = AB / (names[-1] if args.benches_from_last else name)
                js = out / f"{bench}_{name}_{rnd}.json"
                env = _build_env(name)
                t0 = time.perf_counter()
                with open(out / f"{bench}_{name}_{rnd}.log", "w") as log:
                    rc = subprocess.run([sys.executable, *benches[bench], "--json", str(js)], cwd=src, env=env,
                                        stdout=log, stderr=subprocess.STDOUT, timeout=args.timeout).returncode
                if rc == 0 and js.exists():
                    results[name][bench].append(json.loads(js.read_text()))
                print(f"round {rnd + 1} {bench} {name}: rc {rc} in {time.perf_counter() - t0:.0f} s", flush=True)
        # the table after every round: a call that runs out of time keeps the rounds it finished
        _table(names, results, out, final=rnd == args.rounds - 1)
    return 1 if failed else 0


def _checks(args, names: list[str], out: Path) -> bool:
    """Before the benches, on the builds just made: ``--pytest`` runs the last source's tests
    against its build; ``--same-flows`` runs tools/same_flows.py with every source (its own
    tree and build), each compared with the first's file. True if any failed or differed
    (the benches still run: a call keeps its figures)."""
    failed = False  # (each source's ROOT/../shared is .ab/shared: prepare --shared)
    if args.pytest:
        failed |= _check(out, "pytest", names[-1], ["-m", "pytest", "-q", "-p", "no:cacheprovider",
                                                    *shlex.split(args.pytest)])
    if args.same_flows is not None:
        first = out / f"same_flows_{names[0]}.npz"
        for k, name in enumerate(names):
            failed |= _check(out, "same_flows", name,
                             ["tools/same_flows.py", "--device", args.device, *shlex.split(args.same_flows),
                              "--out", str(out / f"same_flows_{name}.npz")] + (["--against", str(first)] if k else []))
    return failed


def _check(out: Path, label: str, name: str, argv: list[str]) -> bool:
    """Python ``argv`` in source ``name``'s tree against its build, logged to
    ``<label>_<name>.log``; prints the rc and the log's last line; True if it failed."""
    log_path = out / f"{label}_{name}.log"
    with open(log_path, "w") as log:
        rc = subprocess.run([sys.executable, *argv], cwd=AB / name, env=_build_env(name), stdout=log,
                            stderr=subprocess.STDOUT).returncode
    last = log_path.read_text().strip().splitlines()[-1:] or ["(no output)"]
    print(f"{label} {name}: rc {rc}: {last[0]}", flush=True)
    return rc != 0


def _build_env(name: str) -> dict:
    """The environment that imports source ``name``'s build (/tmp/ab/<name>)."""
    return dict(os.environ, PYTHONPATH=f"/tmp/ab/{name}", PYTHONUNBUFFERED="1")


def _table(names: list[str], results: dict, out: Path, final: bool) -> None:
    table = []
    base = names[0]
    print(f"\n{'figure' if final else 'figure (rounds so far)':<44}" + "".join(f"{n:>16}" for n in names)
          + "".join(f"{n + '/' + base:>22}" for n in names[1:]))
    for label, bench, path, lower, scale in FIGURES:
        meds = {}
        for n in names:
            vals = [v for v in (_get(r, path) for r in results[n][bench]) if isinstance(v, (int, float))]
            meds[n] = statistics.median(vals) * scale if vals else None
        if all(v is None for v in meds.values()):
            continue
        ratios = {n: (meds[n] / meds[base] if meds[n] and meds[base] else None) for n in names[1:]}
        table.append(dict(figure=label, lower_is_better=lower, medians=meds, ratios=ratios,
                          rounds={n: [_get(r, path) for r in results[n][bench]] for n in names}))
        print(f"{label:<44}" + "".join(f"{(meds[n] or float('nan')):>16.2f}" for n in names)
              + "".join(f"{(ratios[n] or float('nan')):>22.3f}" for n in names[1:]), flush=True)
    (out / "ab_bench.json").write_text(json.dumps(dict(order=names, table=table), indent=1) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("prepare", help="copy the sources of revisions into .ab/ (here, with git)")
    p.add_argument("revs", nargs="+", help="git revisions; WORKTREE for the working tree as it is")
    p.add_argument("--shared", action="store_true",
                   help="copy ../shared/data into .ab/shared (tests and same_flows read the real scans there)")
    r = sub.add_parser("run", help="build and bench every prepared source (on a GPU host)")
    r.add_argument("--out", default=os.environ.get("OUT", "/tmp/ab_out"))
    r.add_argument("--device", default="cuda", choices=["cuda", "cpu"],
                   help="cpu: a smoke test of this script (CPU builds; give small --speed-args/--run-args)")
    r.add_argument("--rounds", type=int, default=2, help="0: only build")
    r.add_argument("--alternate", action="store_true", help="reverse the sources' order every other round")
    r.add_argument("--skip-built", action="store_true", help="keep builds already in /tmp/ab (an earlier run's)")
    r.add_argument("--benches", nargs="+", default=["speed", "run"], choices=["speed", "run", "fresh"])
    r.add_argument("--speed-args", default="--repeats 7 --seq-repeats 2")
    r.add_argument("--run-args", default="--repeat 1")
    r.add_argument("--fresh-args", default="--frames 768 --data /tmp/ab_data",
                   help="bench_run_fresh.py's arguments (with --benches fresh; its --data is bench_run's)")
    r.add_argument("--timeout", type=int, default=200, help="seconds per bench run")
    r.add_argument("--benches-from-last", action="store_true",
                   help="time every build with the last source's bench scripts (their newer options)")
    r.add_argument("--pytest", default="", metavar="ARGS",
                   help="pytest's arguments, run in the last source against its build before the benches "
                        "(e.g. \"-m cuda -n 8 tests/ops\")")
    r.add_argument("--same-flows", default=None, metavar="ARGS",
                   help="tools/same_flows.py's arguments, run with every build, each compared with the first's "
                        "(\"\": its defaults)")
    args = ap.parse_args()
    if args.cmd == "prepare":
        prepare(args.revs, args.shared)
    else:
        sys.exit(run(args))


if __name__ == "__main__":
    main()
