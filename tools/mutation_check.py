"""Does the test suite catch a wrong Floxels? Small deliberate bugs, one at a time, in a scratch copy.

    python tools/mutation_check.py [--only NAME ...] [--python | --cpp] [--json FILE] [--list]

Copies the working tree's files (tracked, and new ones git does not ignore) and the compiled
``python/floxels_ext/_C*.so`` to a scratch directory, with ``../shared`` beside it where this checkout has one (the tests that
read the paper or the real data then run there too), checks that every test subset named
below passes there unchanged, then for each mutation (a ``(file, old text, new text)``
replacement; the old text must occur exactly once) applies it, runs that mutation's tests (a
fast subset per mutation: the tests that guard the code it changes; all of them, so the report
names every test that caught it), and restores the file. A mutation is *caught* when its tests
fail (pytest exit status 1, or 2: a collection error). Prints a table, writes JSON (default
``bench/results/mutation_check.json``) and exits 1 if any mutation was missed, if an entry no
longer applies (its old text is not in the file exactly once: re-point it to the code as it is
now), if a C++ mutation does not build, or if the baseline fails. Every mutation on the list
must be caught (issue 34): add tests, not exceptions.

C++ mutations (files under ``csrc/``, CPU code only: the CUDA kernels cannot be built without a
CUDA toolkit) rebuild the extension in the scratch copy: one full build first (a few minutes on
2 cores), then an incremental one per mutation (the translation units that include the file).
``--python`` / ``--cpp`` run only the Python or only the C++ entries; ``--only`` a named subset
(substrings of the names). Set ``OMP_NUM_THREADS=1`` on a shared machine.
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

E = "tests/estimator/"
PAPER = E + "test_paper_settings.py"
E2E_ONE = E + "test_reference_end_to_end.py::test_solver_matches_reference_over_the_whole_optimisation[crossing]"
READINGS = E + "test_estimator.py::test_readings_match_reference_implementation"
ACCURACY = E + "test_estimator.py::test_end_to_end_accuracy"
RESUME = "tests/lidar/test_run_resume.py"
WEIGHTS = E + "test_loss_weights.py"
ACC = E + "test_accurate_preset.py"
EVT = E + "test_evidence_thresholds.py"
EVID = E + "test_evidence.py"
SIGHT = E + "test_sight.py"
GSIGHT = E + "test_ground_sight.py"
FAR = E + "test_far_coordinates.py"
RUN_FAR = "tests/lidar/test_run_far_coordinates.py"
GROUND_RUN = "tests/lidar/test_ground_returns.py"
REFINE = E + "test_refine.py"
SIDED = E + "test_refine_sided.py"
SEARCH = E + "test_refine_search.py"
ONE_SIDED = E + "test_refine_one_sided.py"
LONG = E + "test_long_windows.py"
SEEN = E + "test_seen_evidence.py"
SPREAD = E + "test_spread.py"
UNSEEN_T = E + "test_unseen.py"
CHECKS_T = E + "test_evidence_checks.py"
HOSTR = E + "test_host_reads.py"
COMPOSE = E + "test_accurate_composition.py"
EVAL = "tests/evaluation/test_eval_scope.py"
AV2 = "tests/evaluation/test_metrics_av2.py"
PREPROC = ["tests/ops/test_lidar_ops.py", "tests/lidar/test_ground_outliers.py", "tests/lidar/test_real_sweeps_preprocess.py"]
QUERY = ["tests/ops/test_dt_query.py", "tests/ops/test_dt_query_observed.py"]

CFG = "python/floxels_ext/estimator/config.py"
PRESETS_PY = "python/floxels_ext/presets.py"  # the preset table (no torch: the Ray driver reads it)
CHECKS_PY = "python/floxels_ext/estimator/evidence_checks.py"
POST_PY = "python/floxels_ext/estimator/post.py"
REF = "python/floxels_ext/reference/estimator.py"
SOLVER = "python/floxels_ext/ops/solver.py"
STOP = "python/floxels_ext/estimator/early_stopping.py"
OUTS = "python/floxels_ext/lidar/io/outputs.py"
RES = "python/floxels_ext/lidar/pipeline/resume.py"
SCANS = "python/floxels_ext/estimator/scans.py"
WINDOWS = "python/floxels_ext/estimator/windows.py"
RECENTRE = "python/floxels_ext/estimator/recentre.py"
RECENTRE_T = "tests/estimator/test_recentre_bounds.py"
GROUP = "python/floxels_ext/estimator/group.py"
POST = "python/floxels_ext/estimator/post.py"
EVIDENCE = "python/floxels_ext/estimator/evidence.py"
SIGHT_PY = "python/floxels_ext/estimator/sight.py"
REFINE_PY = "python/floxels_ext/estimator/refine.py"
GROUP_SUMS = "python/floxels_ext/estimator/group_sums.py"
ARROW = "python/floxels_ext/lidar/io/_arrow.py"
READERS = "python/floxels_ext/lidar/io/readers.py"
ARROW_TESTS = "tests/lidar/test_io_arrow_columns.py"
HOST_READS = "python/floxels_ext/estimator/host_reads.py"
LAYOUT = "python/floxels_ext/lidar/dataset/layout.py"
EVAL_CLI = "python/floxels_ext/evaluation/eval_cli.py"
PREPROC_SET = "python/floxels_ext/lidar/preprocess/settings.py"
DT_LOSS_H = "csrc/kernels/dt_loss.h"
SEGSUM_H = "csrc/kernels/segment_sum.h"
SEGSUM_CPU = "csrc/cpu/segment_sum_cpu.cpp"
SEGSUM_T = "tests/ops/test_segment_sum.py"
RAY_WORKER = "python/floxels_ext/lidar/dataset/ray_worker.py"
RAY_POOL = "python/floxels_ext/lidar/dataset/ray_pool.py"
RAY_RUNNER = "python/floxels_ext/lidar/dataset/ray_runner.py"
MPS = "python/floxels_ext/lidar/dataset/mps.py"
MPS_T = "tests/lidar/test_mps.py"
FORK_T = "tests/lidar/test_fork_server_start.py"
JOIN = "python/floxels_ext/lidar/dataset/engine_start.py"
JOIN_T = "tests/lidar/test_engine_start.py"
ENGINES_T = "tests/lidar/test_run_engines.py::test_engines_same_bytes_whoever_runs_which_task"
TASKS = "python/floxels_ext/lidar/dataset/tasks.py"
RAY_UNIT = "tests/lidar/test_ray_worker.py"
RAY_SAME = "tests/lidar/test_ray.py::test_ray_equals_local_and_warm_pool"
RAY_TAIL = "tests/lidar/test_ray.py::test_tail_tasks_halved_same_outputs"
HALVE = "tests/lidar/test_tasks_halve.py"
ANCHORS = "tests/lidar/test_chunk_anchors.py"
RAY_HALF = "tests/lidar/test_ray.py::test_tail_halves_inside_a_chunk_same_bytes"
ENGINE_COUNTS = "python/floxels_ext/lidar/dataset/engine_counts.py"
RAY_TAIL_PY = "python/floxels_ext/lidar/dataset/ray_tail.py"
TAIL_UNIT = "tests/lidar/test_ray_tail.py"
TAIL_E2E = "tests/lidar/test_ray.py::test_tail_cut_where_the_share_says_same_outputs"
ENGINES_DEFAULT = "tests/lidar/test_run_engines.py::test_default_engines_by_device_and_cores"
RAY_REPORT = "python/floxels_ext/lidar/dataset/ray_report.py"
RAY_PRELOAD = "python/floxels_ext/lidar/dataset/ray_preload.py"
PRELOAD_TEST = "tests/lidar/test_ray_preload.py"
RUN_ARGS = "python/floxels_ext/lidar/pipeline/run_args.py"
NUMPY_FILES = "python/floxels_ext/numpy_files.py"
OSF = "python/floxels_ext/lidar/export/opensceneflow.py"
ACCUMULATE = "python/floxels_ext/lidar/viz/accumulate.py"
OUT_PATHS = "python/floxels_ext/output_paths.py"
API_PY = "python/floxels_ext/estimator/api.py"
DEFAULT_PRESET = "tests/lidar/test_run_cli.py::test_default_preset_is_accurate_and_paper_outputs_say_how_to_resume"
SCORE_ZERO = "tests/estimator/test_evidence.py::test_accurate_score_is_zero_before_the_zeroing"
FAR_SENSOR = "tests/estimator/test_sight.py::test_a_sensor_beyond_any_lidars_reach_is_not_used"

# (name, file, old, new, tests). The first four passed the whole suite before issue 34; of those
# after "issue 46", the eleven marked (46) passed the whole suite before that issue.
MUTATIONS = [
    # ---- issue 44, ninth session: the tail cut to each worker's share of the work left ----
    ("tail share ignores what the worker holds", RAY_TAIL_PY,
     "return left / sum(rates.values()) * rates[worker] - held[worker]", "return left / sum(rates.values()) * rates[worker]",
     [TAIL_UNIT]),
    ("tail shares worked out from the job's start", RAY_TAIL_PY, "return queued_tasks < SHARE_QUEUE * max(1, workers)",
     "return True", [TAIL_UNIT]),
    ("tail cut ignores the share", RAY_TAIL_PY,
     "first = max(0.0, share) if share is not None and frames > share + CUT_MARGIN else None", "first = None", [TAIL_UNIT]),
    ("tail rate counts the first report's frames", RAY_TAIL_PY, "self.since[worker], self.frames[worker] = now, 0",
     "self.since[worker], self.frames[worker] = now, n", [TAIL_UNIT]),
    ("the driver halves where the share says cut", RAY_RUNNER,
     "(h := halve_task(todo_tasks[k], align, TAIL_SPLIT_FRAMES, first))", "(h := halve_task(todo_tasks[k], align, TAIL_SPLIT_FRAMES))",
     [TAIL_E2E]),
    ("the driver's rates never told of frames", RAY_RUNNER, "tail.written(slot.name, sum(frames.values()), time.time())",
     "pass", [TAIL_E2E]),
    ("tasks_run not recorded", RAY_RUNNER,
     'ran.append({"task": todo_tasks[k].label, "worker": slot.name, "outcome": outcome,\n'
     '                            "ended_s": round(time.time() - workers.t0, 3)})', "pass", [TAIL_E2E]),
    # ---- eleventh session: the bad-input sweep (helper qa) and its polish ----
    ("an empty .npy read as a pickle", NUMPY_FILES, 'raise ValueError("empty file (0 bytes)")', "pass",
     ["tests/test_numpy_files.py", "tests/lidar/test_io_poses_preprocess.py"]),
    ("a second opensceneflow export drops the first's scenes", OSF, "kept = _kept_entries(out_dir, set(ids))",
     "kept = ([], [], [])", ["tests/lidar/test_export_opensceneflow.py"]),
    ("--poses with --odometry: odometry silently ignored", RUN_ARGS,
     'if args.poses and getattr(args, "odometry", None):', "if False:", ["tests/lidar/test_user_errors_run.py"]),
    ("--radius without --mode chain silently ignored", ACCUMULATE,
     'if args.radius is not None and args.mode != "chain":', "if False:", ["tests/lidar/test_user_errors_issue30.py"]),
    ("--png f.jpg writes PNG bytes under .jpg", OUT_PATHS,
     "if suffix is not None and p.suffix.lower() != suffix and not p.is_dir():", "if False:",
     ["tests/lidar/test_user_errors_issue30.py"]),
    ("--frames -1: read as the next option", "python/floxels_ext/cli.py", 'out.append(f"--frames={argv[i + 1]}")',
     "out.extend(argv[i:i + 2])", ["tests/lidar/test_run_cli.py::test_a_slice_from_the_end_needs_no_equals_sign"]),
    ("a callback that is no function found after the first frame", API_PY,
     "if callback is not None and not callable(callback):", "if False:", ["tests/estimator/test_user_errors_api.py"]),
    # ---- issue 44, ninth session: Ray's workers a GPU follow the local engines ----
    ("Ray's default share from the most cores a GPU", ENGINE_COUNTS,
     'w = default_engines("cuda", int(min(per_gpu)) if per_gpu else 0, preset)',
     'w = default_engines("cuda", int(max(per_gpu)) if per_gpu else 0, preset)', [RAY_UNIT]),
    ("Ray's default share ignores the preset", RAY_RUNNER, "gpus = gpu_share(nodes, preset_name(args))",
     'gpus = gpu_share(nodes, "paper")', [RAY_UNIT]),
    ("Ray's default share not rounded to Ray's precision", ENGINE_COUNTS, "return math.floor(1e4 / w) / 1e4",
     "return 1 / w", [RAY_UNIT]),
    # ---- issue 42, eighth session: accurate's GPU time (group sums, run bounds), its engines ----
    ("group sums keep a non-finite term's row finite", SEGSUM_CPU, "bad[void_row ? r : r * C + c] = 1;",
     "bad[void_row ? r : r * C + c] = 0;", [E + "test_segment_sums.py", SEGSUM_T]),
    ("group sums clamp every term to 1", GROUP_SUMS, "MAX_FIXED_SUM = float(2 ** 18)", "MAX_FIXED_SUM = 1.0",
     [E + "test_segment_sums.py"]),
    ("seen evidence's runs end where they start", EVIDENCE, "table[1].scatter_(0, torch.where(ends, run, spare), idx)",
     "table[1].scatter_(0, torch.where(starts, run, spare), idx)", [E + "test_seen_evidence.py"]),
    # ---- issue 42, eighth session (av2read): AV2 columns from Arrow buffers, .bin without the GIL ----
    ("an Arrow slice read from its buffer's start", ARROW, "offset=chunk.offset * dt.itemsize", "offset=0",
     [ARROW_TESTS]),
    ("a column with nulls read from its buffer", ARROW, "if arr.null_count or t.id not in _plain_ids():",
     "if t.id not in _plain_ids():", [ARROW_TESTS]),
    ("AV2 rows of mixed column types through to_tensor", ARROW, "any(c.type != t or c.null_count for c in cols)",
     "any(c.null_count for c in cols)", [ARROW_TESTS]),
    ("a .bin that shrank while read passes", READERS, "if got != size:", "if False:",
     [ARROW_TESTS, "tests/lidar/test_io_readers.py"]),
    ("bench_run --data rebuilt every run", "bench/bench_run.py", "if {k: old.get(k) for k in meta} == meta:",
     "if False:", ["tests/test_bench_run_data.py"]),
    ("accurate keeps three engines", ENGINE_COUNTS, 'return ACCURATE_ENGINES if preset == "accurate" else 3', "return 3",
     [ENGINES_DEFAULT, "tests/lidar/test_run_engines.py::test_engine_count_follows_the_preset_in_effect"]),
    # ---- issue 42, tenth session: tasks balanced over the local engines ----
    ("few frames for the engines: tasks of the run's size (42)", "python/floxels_ext/lidar/dataset/tasks.py",
     "want = task_size(-(-todo_frames // (TASKS_PER_ENGINE * engines)), align)", "want = size",
     ["tests/lidar/test_run_engines.py::test_few_frames_for_the_engines_give_smaller_tasks"]),
    ("a sequence on engines not cut at the balanced size (42)", "python/floxels_ext/lidar/dataset/local.py",
     "task_frames = balanced_task_size(len(todo), engines.n, task_frames, align)", "pass",
     ["tests/lidar/test_run_engines.py::test_the_run_cuts_its_tasks_at_the_balanced_size"]),
    ("a dataset on engines not re-cut at the balanced size (42)", "python/floxels_ext/lidar/dataset/run.py",
     "if size != planned:", "if False:",
     ["tests/lidar/test_run_engines.py::test_the_run_cuts_its_tasks_at_the_balanced_size"]),
    # ---- issue 42, seventh session (faracc): accurate as floxels run's default ----
    ("floxels run's default preset paper", RUN_ARGS,
     'return "accurate" if getattr(args, "method", "floxels") == "floxels" else "paper"', 'return "paper"',
     [DEFAULT_PRESET]),
    ("a sensor out of every lidar's reach used", SIGHT_PY, "return math.fsum(g * g for g in gap) > SENSOR_REACH ** 2",
     "return False", [FAR_SENSOR]),
    ("score's explained keeps the hidden groups the zeroing drops", POST, "explained = explained & ~dropped", "pass",
     [SCORE_ZERO, "tests/lidar/test_run_cli.py::test_motion_evidence_fields_switch_and_resume"]),
    # ---- issue 44, seventh session: workers on Ray's preloaded processes ----
    ("preloaded process not stamped", RAY_WORKER, 'self.stamps["preloaded"] = preload.PRELOADED', "pass",
     [PRELOAD_TEST]),
    ("preload names another module", RAY_PRELOAD, '"RAY_preload_python_modules": __name__', '"RAY_preload_python_modules": "torch"',
     [PRELOAD_TEST]),
    ("a worker seeing extra GPUs not reported", RAY_REPORT, '(r.get("cuda_devices") or 0) > len(r["gpus"])', "False",
     [PRELOAD_TEST]),
    # ---- issues 44 / 42, sixth session: chunks anchored at their block, the engines' default ----
    ("chunks of consecutive targets, not blocks", LAYOUT,
     "if out and block_start(i, chunk, origin) == block_start(out[-1][0], chunk, origin):",
     "if out and len(out[-1]) < (chunk or DEFAULT_CHUNK):",
     [ANCHORS]),
    ("chunk anchored at its own first frame", LAYOUT,
     "self.anchor_from = lo if anchor_from is None else min(lo, anchor_from)", "self.anchor_from = lo",
     [ANCHORS, RAY_HALF]),
    ("three engines on any CUDA host", ENGINE_COUNTS, "if cores < THREE_ENGINE_CORES:\n        return 2", "if False:\n        return 2",
     [ENGINES_DEFAULT]),
    # ---- issue 44, fifth session: the warm pool's hand-over, one summary a sequence, the tail ----
    ("claim does not wait for a dropped worker's release", RAY_WORKER,
     "self.handed.wait_for(lambda: self.owner != self.started_for or self.tasked, timeout=HANDOVER_S)", "pass",
     [RAY_UNIT]),
    ("a claim waits only until the dropped worker's run starts", RAY_WORKER,
     "if (self.owner is not None and self.owner == self.started_for and not self.tasked",
     "if (self.owner is not None and self.owner == self.started_for and not self.running", [RAY_UNIT]),
    ("late claims dropped: the job starts new workers beside them", RAY_POOL,
     "            self.late[ref] = (nm, handles[nm])", "            pass", [RAY_UNIT]),
    ("a claim withdrawn by an earlier release is granted", RAY_WORKER, " or job in self.withdrawn:", ":",
     [RAY_UNIT]),
    ("Ray summary parts dropped", RAY_RUNNER, "task_ended(k, outcome, part)", "task_ended(k, outcome, None)",
     [RAY_SAME]),
    ("tail never halved", RAY_RUNNER, "first = cut_at(slot, k)", "first = None", [RAY_TAIL, TAIL_E2E]),
    ("the last tasks not halved", RAY_TAIL_PY, "    if queued_tasks < workers:\n        first = frames / 2",
     "    if False:\n        first = frames / 2", [TAIL_UNIT, RAY_TAIL]),
    ("the last tasks halved past the share", RAY_TAIL_PY, "else min(first, frames / 2)", "else frames / 2", [TAIL_UNIT]),
    ("tail cut at any frame", TASKS, "if (c - a0) % max(1, align) == 0]", "]", [HALVE]),
    ("tail cut leaves an empty half", TASKS, "return None if not (parts[0].todo and parts[1].todo) else",
     "return None if False else", [HALVE]),
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
    ("Adam lr default 0.05 -> 0.1", CFG, "lr: float = 0.05", "lr: float = 0.1", [PAPER, ACCURACY]),
    ("min delta default 0.01 -> 0.001", CFG, "min_delta: float = 0.01", "min_delta: float = 0.001", [PAPER]),
    ("DBSCAN eps default 0.5 -> 1.0", CFG, "dbscan_eps: float = 0.5", "dbscan_eps: float = 1.0", [PAPER]),
    ("DBSCAN min points default 4 -> 5", CFG, "dbscan_min_samples: int = 4", "dbscan_min_samples: int = 5", [PAPER]),
    ("time weights 1/t^2 -> 1/|t|", CFG, "time_weight_power: float = 2.0", "time_weight_power: float = 1.0",
     [PAPER, ACCURACY]),
    ("DT cell default 0.1 -> 0.2", CFG, "dt_cell: float = 0.1 ", "dt_cell: float = 0.2 ", [PAPER]),
    ("voxel default 0.5 -> 0.4", CFG, "voxel_size: float = 0.5", "voxel_size: float = 0.4", [PAPER]),
    ("voxel default 0.5 -> 1.0", CFG, "voxel_size: float = 0.5", "voxel_size: float = 1.0", [ACCURACY]),
    ("default window 5 -> 3 scans", PRESETS_PY, "DEFAULT_NUM_SCANS = 5 ", "DEFAULT_NUM_SCANS = 3 ", [PAPER]),
    ("floxels run's default window (the paper preset's) 5 -> 3", PRESETS_PY, '    "paper": {},',
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
    # (since the resume_plan refactor the plain run and the dataset share this call)
    ("resume plan without the input records", RES, "args.force, inputs=inputs, report=resume_report or report)",
     "args.force, report=resume_report or report)", [RESUME]),
    ("written dataset sequences skipped unchecked", "python/floxels_ext/lidar/dataset/run.py",
     "_check_written_tasks([t for t in tasks if not t.todo], args)", "pass", [RESUME]),
    ("temporaries of other frames swept", OUTS, 'if m and (names is None or m.group("name") in names):', "if m:",
     [RESUME]),

    # ---- issue 46: the code added since (evidence, sight, accurate, refine, re-centring, ...) ----
    # the loss weights through the estimator
    ("lambda_d ignored (46)", GROUP, "weights.append(cfg.lambda_d * cfg.time_weight(t))",
     "weights.append(cfg.time_weight(t))", [WEIGHTS]),
    ("solver ignores flow_norm_loss=False", SOLVER,
     "lg0, lg1 = (cfg.lambda_g_start, cfg.lambda_g_end) if cfg.flow_norm_loss else (0.0, 0.0)",
     "lg0, lg1 = (cfg.lambda_g_start, cfg.lambda_g_end)", [WEIGHTS]),
    ("solver's lambda_g decay fixed at 100", SOLVER, "float(cfg.lambda_g_decay_iters),", "100.0,", [WEIGHTS]),
    # re-centring
    ("sensor positions not re-centred (46)", SCANS, "sensors = [None if s is None else s - recentring.shift for s in sensors]",
     "sensors = [None if s is None else s for s in sensors]", [FAR]),
    ("removed ground not re-centred (46)", SCANS, "return g if g is None or recentring is None else recentring.apply(g)",
     "return g", [FAR]),
    ("re-centring shift chosen again for every window (46)", WINDOWS,
     "recentring=recentrings.setdefault(w.segment, Recentring()),", "recentring=Recentring(),", [FAR]),
    ("re-centring shift off the 60 m grid", RECENTRE, "self.shift = (np.round(mid / RECENTRE_GRID) * RECENTRE_GRID if",
     "self.shift = (mid if", [FAR]),
    ("re-centring subtracts in float32", RECENTRE, "return (t.to(torch.float64) - s).to(torch.float32)",
     "return t.to(torch.float32) - s.to(torch.float32)", [FAR]),
    ("grid origin reported without the shift", RECENTRE, "return [float(o) + float(s) for o, s in zip(origin, self.shift)]",
     "return origin", [FAR]),
    ("re-centring sample bounds taken without a finiteness check", RECENTRE,
     "if np.isfinite(lo).all() and np.isfinite(hi).all():", "if True:", [RECENTRE_T]),
    ("re-centring sample bounds checked at their minimum only", RECENTRE,
     "if np.isfinite(lo).all() and np.isfinite(hi).all():", "if np.isfinite(lo).all():", [RECENTRE_T]),
    ("floxels run: sensors not moved into the chunk's frame", LAYOUT,
     "return None if p is None or anchor is None or p.sensor is None else p.sensor - anchor",
     "return None if p is None or anchor is None or p.sensor is None else p.sensor", [RUN_FAR]),
    ("floxels run: ground not moved into the chunk's frame", LAYOUT,
     "ground = None if p.ground is None else transform_points(p.ground, T)",
     "ground = None if p.ground is None else transform_points(p.ground, p.to_world)", [RUN_FAR, GROUND_RUN]),
    ("floxels run: Floxels drops the scans' ground", "python/floxels_ext/methods.py",
     "sensors=sensors, grounds=ground, callback=deliver)", "sensors=sensors, grounds=None, callback=deliver)",
     [GROUND_RUN]),
    # the accurate preset
    ("accurate without visibility (46)", PRESETS_PY, '"range_mask": True, "visibility": True}',
     '"range_mask": True, "visibility": False}', [ACC]),
    ("accurate without refine_sided (46)", PRESETS_PY, '"refine_sided": True, "refine_search": True',
     '"refine_sided": False, "refine_search": True', [ACC]),
    ("accurate without refine_search", PRESETS_PY, '"refine_search": True, "range_mask"', '"refine_search": False, "range_mask"',
     [ACC]),
    ("accurate without range_mask", PRESETS_PY, '"range_mask": True, "visibility"', '"range_mask": False, "visibility"', [ACC]),
    ("accurate refines every window plainly (refine_max_supports 0)", PRESETS_PY, '"refine_max_supports": 2,',
     '"refine_max_supports": 0,', [ACC]),
    ("accurate windows 11 -> 9 scans", PRESETS_PY, '"accurate": {"num_scans": 11,', '"accurate": {"num_scans": 9,', [ACC]),
    ("long windows refined without the sides' test", POST, "sided=not short,", "sided=False,", [ACC, SIDED]),
    ("refinement never searched", POST, "search=cfg.refine_search,", "search=False,", [ACC, SEARCH]),
    # refine.py
    ("the sided check looks at the past only (46)", REFINE_PY,
     "accept &= ~_worse_on_a_side(([s for s in supports if s.t < 0], [s for s in supports if s.t > 0]),",
     "accept &= ~_worse_on_a_side(([s for s in supports if s.t < 0],),", [SIDED, ACC]),
    ("the sided check looks at the future only", REFINE_PY,
     "accept &= ~_worse_on_a_side(([s for s in supports if s.t < 0], [s for s in supports if s.t > 0]),",
     "accept &= ~_worse_on_a_side(([s for s in supports if s.t > 0],),", [SIDED, ACC]),
    ("a one-sided window's searched start not checked on its halves (47)", REFINE_PY,
     "halves = one_sided_halves(supports) if sided else None", "halves = None", [ONE_SIDED]),
    ("a one-sided window's halves: the nearer scans only (47)", REFINE_PY,
     "return [side[:half], side[half:]] if half else None", "return [side[:half]] if half else None", [ONE_SIDED]),
    ("refinement keeps the start of higher cost", REFINE_PY, "lower = sel & (cur_s < cur)",
     "lower = sel & (cur_s > cur)", [SEARCH, REFINE]),
    ("static clusters refined (speed floor 0)", REFINE_PY, "REFINE_MIN_SPEED = 0.1", "REFINE_MIN_SPEED = 0.0",
     [REFINE, SEARCH]),
    ("cluster means' fixed point at 2^-10 m/frame", SEGSUM_H, "constexpr double kScale = 16777216.0;",
     "constexpr double kScale = 1024.0;", [REFINE, SEGSUM_T]),
    ("cluster means' fixed point not clamped", GROUP_SUMS, "fixed_segment_sum(flow, lab, C, MAX_FIXED_FLOW,",
     "fixed_segment_sum(flow, lab, C, 2.0 ** 28,", [REFINE, SEGSUM_T]),
    ("cluster with a non-finite flow refined", GROUP_SUMS, "MAX_FIXED_FLOW, void_row=True, count=True)",
     "MAX_FIXED_FLOW, void_row=False, count=True)", [REFINE, SEGSUM_T]),
    ("fixed-point sums count a row's first-row terms only", SEGSUM_CPU, "if (count) ++n[r];",
     "if (count && r > 0) ++n[r];", [REFINE, SEGSUM_T]),
    ("fixed-point sums not clamped above", SEGSUM_H, "(x > limit ? limit : x)", "x", [SEGSUM_T]),
    # the evidence test
    ("evidence_ratio default 0.05 -> 0.25 (46)", CFG, "evidence_ratio: float = 0.05", "evidence_ratio: float = 0.25",
     [EVT]),
    ("evidence_margin default 0.02 -> 0.01", CFG, "evidence_margin: float = 0.02", "evidence_margin: float = 0.01",
     [EVT]),
    ("all unclustered points in one evidence group (46)", POST,
     "ev = run_evidence(problem.points, flow, problem.labels, problem.corners.corner_idx[:, 0],",
     "ev = run_evidence(problem.points, flow, problem.labels, torch.zeros_like(problem.corners.corner_idx[:, 0]),",
     [EVT]),
    ("group_ids: unclustered points keyed by x only", EVIDENCE,
     "key = (ic[:, 2] << (2 * _AXIS_BITS)) | (ic[:, 1] << _AXIS_BITS) | ic[:, 0]", "key = ic[:, 0]", [EVT, EVID]),
    ("estimator's evidence margin not the config's", POST, "margin=cfg.evidence_margin,", "margin=0.02,", [EVT, ACC]),
    ("estimator's evidence ratio not the config's", POST, "margin=cfg.evidence_margin, ratio=cfg.evidence_ratio,",
     "margin=cfg.evidence_margin, ratio=0.05,", [EVT, ACC]),
    ("evidence weights not normalised", EVIDENCE, "norm = [float(w) / wsum for w in weights]",
     "norm = [float(w) for w in weights]", [EVT]),
    # sight.py
    ("SEEN_MARGIN 0.5 -> 2.0 m (46)", SIGHT_PY, "SEEN_MARGIN = 0.5 ", "SEEN_MARGIN = 2.0 ", [SIGHT]),
    ("range band in 3-D range, not horizontal", SIGHT_PY,
     "r = torch.hypot(rel[:, :, 0].index_select(0, sel), rel[:, :, 1].index_select(0, sel))",
     "r = torch.linalg.vector_norm(rel.index_select(0, sel), dim=-1)", [SIGHT]),
    ("range image bins 2 degrees", SIGHT_PY, "AZ_BIN = math.radians(0.5)", "AZ_BIN = math.radians(2.0)", [SIGHT]),
    ("removed ground left out of the range images", SIGHT_PY,
     "with_ground = image and ground is not None and ground.shape[0] > 0", "with_ground = False", [GSIGHT]),
    ("empty bins never seen through (47)", SIGHT_PY, "THROUGH_BINS = 4 ", "THROUGH_BINS = 0 ",
     [SIGHT, E + "test_sliding_side.py"]),
    ("seen through past a surface at the place's range (47)", SIGHT_PY, "ok = side >= far", "ok = side >= 0",
     [SIGHT]),
    ("seen through under a gap with returns higher up (47)", SIGHT_PY,
     "above = ok[..., 0] | ((side[..., 0] < 0) & (ie > tops.view(-1)[idx // NUM_EL]))",
     "above = ok[..., 0] | (side[..., 0] < 0)", [SIGHT]),
    ("seen through beside a return at the place's range (47)", SIGHT_PY,
     "return through & ((v < 0) | (v >= far[..., None])).all(dim=-1)", "return through", [SIGHT]),
    # issue 42: the seen-through test's look-ups in one gather, the nearest return by argmax
    ("seen through: the farthest of the bins above, not the nearest (42)", SIGHT_PY,
     "first = (v >= 0).to(torch.uint8).argmax(dim=-1, keepdim=True)",
     "first = (v >= 0).to(torch.uint8).flip(-1).argmax(dim=-1, keepdim=True).neg().add(THROUGH_BINS - 1)",
     [SIGHT]),
    ("seen through: one side's bins only (42)", SIGHT_PY, "through = (ret < 0) & above & ok[..., 1]",
     "through = (ret < 0) & above", [SIGHT]),
    ("seen through on the neighbours' farthest return (47)", SIGHT_PY,
     "near = torch.where(img >= 0, near, torch.full_like(near, -1.0))", "near = img", [SIGHT]),
    # issue 47: the accurate preset's new fields and the code they switch on
    ("accurate regularisers by count (47)", PRESETS_PY, '"reg_scale": "weights", "max_offset"', '"reg_scale": "support", "max_offset"',
     [ACC]),
    ("accurate windows not cut at the ends (47)", PRESETS_PY, '"max_offset": 5,', '"max_offset": 0,', [ACC]),
    ("accurate without evidence_seen_mean (47)", PRESETS_PY, '"evidence_seen_mean": True,', '"evidence_seen_mean": False,',
     [ACC]),
    ("accurate without evidence_keep_unseen (47)", PRESETS_PY, '"evidence_keep_unseen": True,',
     '"evidence_keep_unseen": False,', [ACC]),
    ("accurate without refine_level (47)", PRESETS_PY, '"refine_level": True,', '"refine_level": False,', [ACC]),
    ("accurate without refine_spread (47)", PRESETS_PY, '"refine_spread": 1.0,', '"refine_spread": 0.0,', [ACC]),
    ("accurate without evidence_upright (47)", PRESETS_PY, '"evidence_upright": True,', '"evidence_upright": False,',
     [ACC]),
    ("upright against the whole flow's length (47)", CHECKS_PY, "return f[:, 2].abs() > f[:, :2].norm(dim=1)",
     "return f[:, 2].abs() > f.norm(dim=1)", [CHECKS_T]),
    ("upright clusters by each point's own flow (47)", CHECKS_PY,
     "f = torch.where((lab >= 0)[:, None], mean[lab.clamp_min(0)], flow)", "f = flow", [CHECKS_T]),
    ("upright verdict not applied to the flow (47)", POST_PY,
     "flow = torch.where(up[:, None], torch.zeros_like(flow), flow)", "pass", [CHECKS_T]),
    ("far test keeps the nearest scans (47)", CHECKS_PY,
     "far = [float(w) if abs(float(t)) > near * (1 + 1e-6) else 0.0 for t, w in zip(offsets, weights)]",
     "far = [float(w) for t, w in zip(offsets, weights)]", [CHECKS_T]),
    ("weights scale not normalised to the paper's 4 (47)", CFG,
     "return 4.0 * sum(self.time_weight(t) for t in offsets) / ref", "return sum(self.time_weight(t) for t in offsets)",
     [LONG]),
    ("max_offset ignored (47)", WINDOWS, "if max_offset > 0:", "if False:", [LONG]),
    ("seen_mean rescues groups that follow the sensor (47)", EVIDENCE,
     "rescued &= not_following", "pass", [SEEN]),
    ("seen_mean's margin that of the whole window (47)", EVIDENCE,
     "(margin * noise).to(rz_n.dtype)", "(margin + 0 * noise).to(rz_n.dtype)", [SEEN]),
    ("hidden groups kept wherever they land (47)", "python/floxels_ext/estimator/unseen.py",
     "LANDING_SHARE = 0.5", "LANDING_SHARE = 9.0", [UNSEEN_T]),
    ("merged host reads handed to the wrong problems (47)", HOST_READS,
     "values = iter(_read([t for want in asked.values() for t in want]))",
     "values = iter(_read([t for want in asked.values() for t in want])[::-1])", [HOSTR]),
    # eval's scoring scope
    ("eval scores every point by default", EVAL_CLI,
     'mask = z["mask"] if "mask" in z.files and not all_points else None', "mask = None", [EVAL]),
    ("eval counts no left-out point", EVAL_CLI, "left_out += int((~mask).sum())", "left_out += 0", [EVAL]),
    # ground removal (floxels run's preprocessing; its defaults are the AV2 protocol's and README's)
    ("ground threshold default 0.3 -> 0.5 m", PREPROC_SET, "ground_threshold: float = 0.3 ",
     "ground_threshold: float = 0.5 ", PREPROC),
    ("ground window default 8 -> 4 m", PREPROC_SET, "ground_window: float = 8.0 ", "ground_window: float = 4.0 ",
     PREPROC),
    ("ground rise cap default 0.5 m -> none", PREPROC_SET, "ground_max_rise: float | None = 0.5 ",
     "ground_max_rise: float | None = None ", PREPROC),

    # ---- twelfth session: floxels run --mps (lidar/dataset/mps.py) ----
    ("--mps: the user's MPS replaced by a private one", MPS, "    if env.get(PIPE):\n", "    if False:\n", [MPS_T]),
    ("--mps: a daemon whose CUDA client failed still used", MPS,
     "probe = subprocess.run(PROBE_ARGS, env=env, capture_output=True, timeout=timeout).returncode",
     "probe = 0 * subprocess.run(PROBE_ARGS, env=env, capture_output=True, timeout=timeout).returncode", [MPS_T]),
    ("--mps: on the CPU too", MPS, 'if device is not None and not device.startswith("cuda"):', "if False:", [MPS_T]),
    ("--mps: an option of the tasks", TASKS, '"keep_workers", "engines", "mps"}', '"keep_workers", "engines"}',
     [MPS_T]),
    # ---- thirteenth session: the fork server started before the run imports torch ----
    ("fork server early for one engine too", "python/floxels_ext/lidar/dataset/run.py",
     "return args.engines > 1", "return args.engines >= 1", [FORK_T]),
    ("fork server never started early", "python/floxels_ext/lidar/dataset/run.py",
     "    if _forks_ahead(args):\n", "    if False:\n", [FORK_T]),
    ("fork server early with every GPU hidden", "python/floxels_ext/lidar/dataset/run.py",
     'not in ("", "-1") and os.path.exists("/dev/nvidiactl")', 'not in ("",) and os.path.exists("/dev/nvidiactl")',
     [FORK_T]),
    ("fork server early on a CPU-only host", "python/floxels_ext/lidar/dataset/run.py",
     'and os.path.exists("/dev/nvidiactl")', "", [FORK_T]),
    ("the early fork server's OSError crashes the run", "python/floxels_ext/lidar/pipeline/worker_processes.py",
     "        forkserver.ensure_running()\n    except OSError:", "        forkserver.ensure_running()\n    except ValueError:",
     [FORK_T]),
    # ---- thirteenth session: when the engines joined (run_summary.json's engines_start) ----
    ("engines joined at the first engine's first frame", JOIN, "if len(self.first) == self.n:",
     "if len(self.first) >= 1:", [JOIN_T]),
    ("failed frames counted in the steady rate", JOIN, "        if ok:\n            self.written += 1",
     "        if True:\n            self.written += 1", [JOIN_T]),
    ("engines_start not in the sequence's summary", "python/floxels_ext/lidar/dataset/local.py",
     'merged["engines_start"] = res["start"]', "pass", [ENGINES_T]),
    ("engines_start dropped by the summary's render", "python/floxels_ext/lidar/dataset/summary.py",
     'if "engines_start" in part:', "if False:", [ENGINES_T]),

    # ---- issue 47: a one-sided window's follower hidden behind its own moved group ----
    ("self-occluded follower: any scan hiding it counts", "python/floxels_ext/estimator/evidence.py",
     "mine = (own != 0) & (own == occluded)", "mine = own != 0", ["tests/estimator/test_follow_occluded.py"]),
    ("self-occluded follower: any nearer return counts", "python/floxels_ext/estimator/sight.py",
     "& (near >= 0) & ((near - r_self).abs() <= SELF_MATCH))", "& (near >= 0))",
     ["tests/estimator/test_follow_occluded.py"]),
    ("self-occluded follower: the moved group need not be in front", "python/floxels_ext/estimator/sight.py",
     "(r_self < pr - SEEN_MARGIN)", "(r_self < pr + 1e9)", ["tests/estimator/test_follow_occluded.py"]),

    # ---- C++ (csrc/kernels/solver.h: stage 3, CPU and CUDA) ----
    ("stage 3 takes a read-ahead bias pair of another iteration", "csrc/kernels/solver.h",
     "if (ahead_it == it) {", "if (ahead_it <= it) {", ["tests/ops/test_solver.py"]),

    # ---- C++ (csrc/kernels/dt_loss.h: the evidence test and the residuals, CPU and CUDA) ----
    ("evidence test gain >= threshold (46)", DT_LOSS_H, "return gain > thr;  // false for NaN",
     "return gain >= thr;  // false for NaN", [EVT]),
    ("evidence threshold the smaller of margin and ratio", DT_LOSS_H, "thr = thr < margin ? margin : thr;",
     "thr = thr < margin ? thr : margin;", [EVT]),
    ("evidence counts scans that could not see the point", DT_LOSS_H,
     "const T c = counts(bits, k) ? s.coef : T(0);", "const T c = s.coef;", QUERY + [GSIGHT]),
]


def is_cpp(path: str) -> bool:
    return path.startswith("csrc/")


def scratch_copy(dest: Path) -> None:
    # tracked files and new ones not ignored (tests written but not committed yet)
    files = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                           check=True, capture_output=True).stdout
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
    shared = ROOT.parent / "shared"
    if shared.is_dir():  # the tests find ../shared (the paper, the real data) as in the checkout
        (dest.parent / "shared").symlink_to(shared.resolve())


def build(root: Path, timeout: float) -> tuple[bool, float, str]:
    """(built, seconds, the output's tail) of tools/dev_build.sh in the scratch copy."""
    t0 = time.perf_counter()
    env = {**os.environ, "PYTHON": sys.executable}
    try:
        r = subprocess.run(["bash", "tools/dev_build.sh"], cwd=root, env=env, capture_output=True, text=True,
                           timeout=timeout)
        ok, out = r.returncode == 0, r.stdout + r.stderr
    except subprocess.TimeoutExpired:
        ok, out = False, "build timed out"
    return ok, time.perf_counter() - t0, "\n".join(out.strip().splitlines()[-15:])


def run_tests(root: Path, tests: list[str], timeout: float, first_failure: bool = False):
    """(pytest's exit status, seconds, its last line, the failed tests' names); status -1: timeout."""
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
    kind = ap.add_mutually_exclusive_group()
    kind.add_argument("--python", action="store_true", help="only the Python mutations (no build)")
    kind.add_argument("--cpp", action="store_true", help="only the C++ mutations (builds the extension)")
    ap.add_argument("--list", action="store_true", help="list the mutations and exit")
    ap.add_argument("--json", default=str(ROOT / "bench" / "results" / "mutation_check.json"))
    ap.add_argument("--timeout", type=float, default=900.0, help="s per test run or build")
    args = ap.parse_args()
    muts = [m for m in MUTATIONS if (not args.only or any(o in m[0] for o in args.only))
            and not (args.python and is_cpp(m[1])) and not (args.cpp and not is_cpp(m[1]))]
    if args.list:
        for name, path, _, _, tests in muts:
            print(f"{name:<64} {path:<48} {' '.join(tests)}")
        print(f"{len(muts)} mutation(s)")
        return 0
    if not muts:
        print("no mutation selected", file=sys.stderr)
        return 1
    # entries that no longer match the code fail loudly, before anything runs
    stale = []
    for name, path, old, _, _ in muts:
        target = ROOT / path
        n = target.read_text().count(old) if target.is_file() else -1
        if n != 1:
            stale.append(name)
            print(f"STALE   {name}: the text to replace occurs {max(n, 0)} times in {path}"
                  f"{'' if n >= 0 else ' (no such file)'}: re-point the entry to the code as it is now",
                  file=sys.stderr)
    rows, ok = [dict(name=n, caught=None, error="stale") for n in stale], not stale
    muts = [m for m in muts if m[0] not in stale]
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="floxels_mutation_") as tmp:
        root = Path(tmp) / "repo"
        root.mkdir()
        scratch_copy(root)
        pristine = None
        if any(is_cpp(m[1]) for m in muts):
            built, secs, tail = build(root, args.timeout)
            print(f"build of the unmutated copy: {'done' if built else 'FAILED'} in {secs:.0f} s", flush=True)
            if not built:
                print(tail, file=sys.stderr)
                return 1
            pristine = {Path(so).name: Path(so).read_bytes() for so in glob.glob(str(root / "python/floxels_ext/_C*.so"))}
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
            target.write_text(text.replace(old, new))
            build_s = 0.0
            try:
                if is_cpp(path):
                    built, build_s, tail = build(root, args.timeout)
                    if not built:
                        ok = False
                        rows.append(dict(name=name, file=path, tests=tests, caught=None, error="does not build",
                                         build_seconds=round(build_s, 1)))
                        print(f"ERROR   {build_s:6.0f} s  {name}: the mutated code does not build\n{tail}", flush=True)
                        continue
                rc, secs, last, failed = run_tests(root, tests, args.timeout)
            finally:
                target.write_text(text)
                if pristine is not None and is_cpp(path):  # the next build recompiles what this one changed
                    for so_name, data in pristine.items():
                        (root / "python/floxels_ext" / so_name).write_bytes(data)
            caught = rc in (1, 2, -1)  # tests failed, collection failed, or the run hung
            if rc not in (0, 1, 2, -1):  # a usage error (e.g. a test path that no longer exists)
                ok = False
                rows.append(dict(name=name, file=path, tests=tests, caught=None, error=f"pytest exit {rc}: {last}"))
                print(f"ERROR   {secs:6.0f} s  {name}: pytest exit {rc} ({last})", flush=True)
                continue
            ok &= caught
            rows.append(dict(name=name, file=path, tests=tests, caught=caught, seconds=round(secs, 1),
                             build_seconds=round(build_s, 1), pytest=last, failed=failed))
            how = "caught" if caught else "MISSED"
            extra = f" + build {build_s:.0f} s" if build_s else ""
            print(f"{how:<7} {secs:6.0f} s{extra}  {name}  ({last}; {', '.join(failed)})", flush=True)
    n_caught = sum(1 for r in rows if r["caught"])
    total_s = time.perf_counter() - t_all
    print(f"\n{n_caught} of {len(rows)} mutations caught in {total_s / 60:.1f} min"
          + (f"; {len(stale)} stale entr{'y' if len(stale) == 1 else 'ies'}" if stale else ""))
    os.makedirs(os.path.dirname(args.json), exist_ok=True)
    with open(args.json, "w") as fh:
        json.dump(dict(caught=n_caught, total=len(rows), seconds=round(total_s), rows=rows), fh, indent=1)
    print(f"wrote {args.json}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
