"""``floxels eval PRED_DIR GT_DIR``: score predicted flows against ground truth.

Ground truth: ``GT_DIR/NNNNNN.npz`` with ``points`` and ``flow`` (optional ``classes``, ``ground``,
``dynamic``, ``pose``), as ``floxels simulate`` writes them or a dataset converted to that format.
Predictions: ``PRED_DIR/NNNNNN.npz`` with ``flow`` in the same point order, as ``floxels run``
writes them (those also record ``method`` and ``options``, which is how swapped arguments are
recognised). Metrics: ``metrics.evaluate_sequence``; with ``--categories av2`` the classes are
Argoverse 2 label classes, mapped to the official evaluation's meta-classes, and the official
35 m evaluation box is on unless ``--no-eval-box``.

What is scored (issue 30): by default only the points each prediction says its run optimised
(the ``mask`` that ``floxels run`` writes; points cropped or removed as ground carry flow 0, not
an estimate, and scoring them made a 7-frame run's dynamic EPE 0.447 instead of 0.159);
``--all-points`` scores every point; predictions without ``mask`` are scored on every point.
The frames scored are those PRED_DIR holds (a partial run, ``floxels run --frames A:B``) or
``--frames A:B`` of GT_DIR; the report names both.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from floxels_ext.cli import CLIError

__all__ = ["add_parser", "run", "load_eval_pair", "format_metrics"]

_PRED_MARKS = ("method", "options")  # keys only `floxels run` outputs hold
_GT_MARKS = ("classes", "instance", "dynamic", "ground")  # keys only ground truth holds


def add_parser(sub) -> None:
    p = sub.add_parser("eval", help="score predicted flows against ground truth",
                       description="Compare PRED_DIR/NNNNNN.npz ('flow', same point order) with GT_DIR/NNNNNN.npz "
                                   "('points', 'flow', optional 'classes', 'dynamic', 'ground', 'pose') and print "
                                   "all metrics.")
    p.add_argument("pred_dir", metavar="PRED_DIR", help="predictions (e.g. the OUT_DIR of floxels run)")
    p.add_argument("gt_dir", metavar="GT_DIR", help="ground truth (e.g. the OUT_DIR of floxels simulate)")
    p.add_argument("--json", metavar="FILE", help="also write the metrics as JSON")
    p.add_argument("--frames", metavar="A:B", help="score only these frames of GT_DIR (Python slice); each needs "
                   "its prediction. Default: the frames PRED_DIR holds (a partial run scores its frames)")
    p.add_argument("--all-points", action="store_true",
                   help="score every point of a prediction; by default only the points the run optimised are "
                        "scored (its 'mask': points the crop or ground removal left out have flow 0 and are not "
                        "estimates)")
    p.add_argument("--include-ground", action="store_true", help="also score ground points (excluded by default)")
    p.add_argument("--categories", metavar="MAP",
                   help="GT 'classes' are dataset categories: 'av2' (Argoverse 2 label classes, 0 = background, "
                        "merged into meta-classes as the official evaluation does, its ignored categories left "
                        "out) or a JSON file {\"id\": \"car\"|...|null}; default: classes are meta-class ids "
                        "0..4 (or 'av2' if GT_DIR/sequence.json says \"dataset\": \"av2\")")
    box = p.add_mutually_exclusive_group()
    from floxels_ext.cli_types import positive_float

    box.add_argument("--eval-box", type=positive_float, metavar="METRES",
                     help="score only points with max(|x|,|y|) < METRES in their scan's frame "
                          "(default: 35 for AV2 categories, else off)")
    box.add_argument("--no-eval-box", action="store_true", help="score points at any distance")
    p.set_defaults(func=run)


# ----------------------------------------------------------------------------- loading
def _keys(path: Path) -> set[str]:
    from floxels_ext.numpy_files import open_npz  # (numpy: not at the top, for a fast `floxels --help`)

    try:
        with open_npz(path) as z:
            return set(z.files)
    except Exception:  # unreadable files are reported by the full read below
        return set()


def _check_not_swapped(pred_dir, gt_dir, pred_first: Path, gt_first: Path) -> None:
    """A GT directory written by `floxels run` is a prediction; with a PRED directory that looks
    like ground truth the arguments are swapped."""
    pk, gk = _keys(pred_first), _keys(gt_first)
    gt_is_pred = any(k in gk for k in _PRED_MARKS)
    pred_is_gt = "points" in pk and not any(k in pk for k in _PRED_MARKS) and any(k in pk for k in _GT_MARKS)
    if gt_is_pred and pred_is_gt:
        raise CLIError(f"the arguments look swapped: GT_DIR {gt_dir} holds predictions written by 'floxels run' "
                       f"({gt_first.name} records 'method'), and PRED_DIR {pred_dir} holds ground truth "
                       f"({pred_first.name} has 'points' and {sorted(k for k in _GT_MARKS if k in pk)}); "
                       f"usage: floxels eval PRED_DIR GT_DIR, i.e. floxels eval {gt_dir} {pred_dir}")
    if gt_is_pred:
        raise CLIError(f"GT_DIR {gt_dir} holds predictions written by 'floxels run' ({gt_first.name} records "
                       f"'method'), not ground truth; usage: floxels eval PRED_DIR GT_DIR")


def _read_gt(path: Path, raw_classes: bool):
    """A ground-truth frame; with ``raw_classes`` its classes are kept as stored (dataset ids)."""
    import numpy as np

    from floxels_ext.evaluation import seqio
    from floxels_ext.numpy_files import open_npz

    if not raw_classes:
        try:
            return seqio.read_frame(path, require=("points", "flow"))
        except seqio.SequenceFormatError as e:
            if "'classes'" in str(e):
                raise CLIError(f"{e}; if these are dataset categories, pass --categories av2 "
                               f"or --categories MAP.json") from None
            raise
    if not path.is_file():
        raise CLIError(f"missing frame file {path}")
    try:
        with open_npz(path) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as e:  # zip/npy errors come in many types
        raise CLIError(f"{path}: cannot read as .npz ({e})") from None
    missing = [k for k in ("points", "flow") if k not in arrays]
    if missing:
        raise CLIError(f"{path}: missing key(s) {missing} (present: {sorted(arrays)})")
    classes = arrays.pop("classes", None)
    frame = seqio.Frame(**seqio._validate(arrays, str(path)))
    if classes is not None:
        classes = np.asarray(classes)
        if classes.shape != (len(frame),) or not np.issubdtype(classes.dtype, np.integer):
            raise CLIError(f"{path}: 'classes' must be ({len(frame)},) integers, got {classes.shape} {classes.dtype}")
        frame.classes = classes.astype(np.int64)
    return frame


def _read_pred(pp: Path, gp: Path, n: int, all_points: bool = True):
    """(predicted flow, mask of the points to score) of one frame, checked against its ground
    truth's point count. The mask is the prediction's ``mask`` (the points its run optimised)
    unless ``all_points`` or the file has none (then every point)."""
    import numpy as np

    from floxels_ext.numpy_files import open_npz

    if not pp.is_file():
        raise CLIError(f"missing predicted frame {pp} (ground truth {gp} exists)")
    try:
        with open_npz(pp) as z:
            if "flow" not in z.files:
                raise CLIError(f"{pp}: missing key(s) ['flow'] (present: {sorted(z.files)})")
            flow = z["flow"]
            mask = z["mask"] if "mask" in z.files and not all_points else None
    except CLIError:
        raise
    except Exception as e:
        raise CLIError(f"{pp}: cannot read as .npz ({e})") from None
    if flow.ndim != 2 or flow.shape[1] != 3 or not np.issubdtype(flow.dtype, np.number):
        raise CLIError(f"{pp}: 'flow' must have shape (N, 3) numbers, got {flow.shape} {flow.dtype}")
    if flow.shape[0] != n:
        raise CLIError(f"{pp}: 'flow' has {flow.shape[0]} points but {gp} has {n}")
    if mask is None:
        mask = np.ones(n, bool)
    elif mask.shape != (n,) or mask.dtype != np.bool_:
        raise CLIError(f"{pp}: 'mask' must be ({n},) bools, got {mask.shape} {mask.dtype}")
    bad = mask & ~np.isfinite(flow).all(axis=1)
    if bad.any():
        raise CLIError(f"{pp}: 'flow' has {int(bad.sum())} NaN/inf vector(s) of {n} (first at point "
                       f"{int(np.argmax(bad))}); predictions must be finite, since a NaN would silently drop "
                       f"its points (and whole classes) from the metrics")
    return np.asarray(flow, dtype=np.float64), mask


def _check_one_run(pred_dir, paths: dict[int, Path]) -> None:
    """Refuse predictions written with different settings (``floxels run --force --frames``
    with other options over part of an OUT_DIR left it mixed, and the mix was scored as one
    method). Outputs without a ``settings`` record (other writers) are not compared."""
    from floxels_ext.numpy_files import open_npz

    groups: dict[str, list[int]] = {}
    for i, p in paths.items():
        try:
            with open_npz(p) as z:
                key = json.dumps(json.loads(str(z["settings"])), sort_keys=True) if "settings" in z.files else None
        except Exception:  # unreadable: reported by the full read
            continue
        if key is not None:
            groups.setdefault(key, []).append(i)
    if len(groups) > 1:
        (ka, fa), (kb, fb) = sorted(groups.items(), key=lambda kv: kv[1][0])[:2]
        a, b = json.loads(ka), json.loads(kb)
        diff = [f"{k}: {a.get(k)!r} vs {b.get(k)!r}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
        raise CLIError(f"{pred_dir} mixes outputs written with {len(groups)} different settings: {_frame_list(fa)} "
                       f"and {_frame_list(fb)} differ in {'; '.join(diff)[:300] or 'their settings'}; scores of the "
                       f"mix would be no one run's. Recompute the odd ones with the same options (floxels run "
                       f"--force), or score one part with --frames")


def _numbered(d) -> dict[int, Path]:
    """Frame files NNNNNN.npz of a prediction directory by number (any subset: a partial run)."""
    from floxels_ext.evaluation.seqio import _FRAME_RE

    return {int(m.group(1)): p for p in Path(d).iterdir() if (m := _FRAME_RE.match(p.name))}


def _rows(frame, keep):
    """The ground-truth frame restricted to the rows ``keep``."""
    from floxels_ext.evaluation import seqio

    return seqio.Frame(**{k: (v if k == "pose" else v[keep]) for k, v in frame.arrays().items()})


def load_eval_pair(pred_dir, gt_dir, raw_classes: bool = False, frames: str | None = None,
                   all_points: bool = False, info: dict | None = None):
    """Ground-truth frames and matching predicted flows, restricted to the points to score;
    errors name the offending file.

    ``raw_classes``: keep the ground truth's ``classes`` as stored (dataset category ids, for a
    category map) instead of requiring meta-class ids 0..4. ``frames``: ``A:B`` over GT_DIR's
    frames (each must have a prediction); default: the frames PRED_DIR holds. ``all_points``:
    score every point, not only those the run optimised (the predictions' ``mask``). ``info``
    (filled in): the frames scored, the points left out."""
    import numpy as np

    from floxels_ext.evaluation import seqio
    from floxels_ext.lidar.pipeline.run_args import parse_frame_range

    for d, what in ((pred_dir, "prediction"), (gt_dir, "ground-truth")):
        if not Path(d).is_dir():
            exists = Path(d).exists()
            raise CLIError(f"{d} is not a directory" if exists else f"{what} directory {d} does not exist")
    gt_paths = seqio.list_frames(gt_dir)
    pred_paths = _numbered(pred_dir)
    if not pred_paths:
        raise CLIError(f"{pred_dir} holds no predicted frame files (expected NNNNNN.npz, as floxels run writes)")
    _check_not_swapped(pred_dir, gt_dir, pred_paths[min(pred_paths)], gt_paths[0])
    extra = sorted(k for k in pred_paths if k >= len(gt_paths))
    if extra:
        raise CLIError(f"{pred_dir} has frame {pred_paths[extra[0]].name} but {gt_dir} only {len(gt_paths)} "
                       f"frames (0..{len(gt_paths) - 1}); no ground truth for it")
    if frames is not None:
        start, stop = parse_frame_range(frames, len(gt_paths))
        chosen = list(range(start, stop))
        missing = [k for k in chosen if k not in pred_paths]
        if missing:
            raise CLIError(f"--frames {frames}: {len(missing)} of the {len(chosen)} chosen frames have no prediction "
                           f"in {pred_dir} (first: {seqio.frame_path(pred_dir, missing[0]).name})")
    else:
        chosen = sorted(pred_paths)
    _check_one_run(pred_dir, {i: pred_paths[i] for i in chosen})
    out_frames, preds = [], []
    total = left_out = 0
    for i in chosen:
        gp = gt_paths[i]
        gt = _read_gt(gp, raw_classes)
        flow, mask = _read_pred(pred_paths[i], gp, len(gt), all_points)
        total += len(gt)
        if not mask.all():
            left_out += int((~mask).sum())
            gt, flow = _rows(gt, mask), flow[mask]
        preds.append(np.ascontiguousarray(flow))
        out_frames.append(gt)
    if info is not None:
        info.update(frames=chosen, gt_frames=len(gt_paths), points=total, not_optimised=left_out,
                    scored_points="all" if all_points else "optimised")
    return preds, out_frames


# ----------------------------------------------------------------------------- output
def _fmt(v, pct=False) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return f"{100 * v:.2f}%" if pct else f"{v:.4f}"


def _frame_list(frames: list[int]) -> str:
    """0-6 as '000000..000006'; gaps listed."""
    runs, start = [], None
    for k, f in enumerate(frames):
        if start is None:
            start = f
        if k + 1 == len(frames) or frames[k + 1] != f + 1:
            runs.append(f"{start:06d}" if start == f else f"{start:06d}..{f:06d}")
            start = None
    return ", ".join(runs[:6]) + (" ..." if len(runs) > 6 else "")


def format_metrics(m: dict) -> str:
    """Human-readable tables of ``metrics.evaluate_sequence`` output."""
    from floxels_ext.evaluation.metrics import ANGLE_MIN_NORM

    head = (f"{m['num_frames']} frames, {m['num_points']} points "
            f"({m['dynamic_count']} dynamic, {m['static_count']} static)")
    scope = []
    if "frames_scored" in m:
        scope.append(f"frames {_frame_list(m['frames_scored'])} of the ground truth's {m['gt_frames']}")
    if m.get("scored_points") == "optimised":
        scope.append(f"only the points the run optimised (its 'mask'); {m['not_optimised_count']} of the "
                     f"{m['frame_points']} points of these frames were cropped or removed as ground by the run and "
                     f"are left out; --all-points scores them too")
    elif m.get("scored_points") == "all":
        scope.append("every point, also those the run did not optimise (--all-points)")
    if m.get("category_map"):
        scope.append(f"{m['category_map']} categories, {m.get('ignored_count', 0)} points of ignored categories left out")
    if m.get("eval_box") is not None:
        scope.append(f"{m.get('outside_box_count', 0)} points outside the {m['eval_box']:g} m evaluation box left out")
    lines = [head] + [f"  ({s})" for s in scope] + [""]
    lines.append(f"{'subset':<10}{'EPE (m)':>10}{'Acc5':>10}{'Acc10':>10}{'Outliers':>10}{'Angle(rad)*':>13}")
    for s in ("dynamic", "static"):
        lines.append(f"{s:<10}{_fmt(m[s + '_epe']):>10}{_fmt(m[s + '_acc5'], True):>10}"
                     f"{_fmt(m[s + '_acc10'], True):>10}{_fmt(m[s + '_outliers'], True):>10}"
                     f"{_fmt(m[s + '_angle']):>13}")
    n_ang = m.get("dynamic_angle_count", 0) + m.get("static_angle_count", 0)
    lines.append(f"* angle between predicted and true 3D flow, only where both exceed {ANGLE_MIN_NORM:g} m/frame "
                 f"({n_ang} points; {m.get('dynamic_angle_count', 0)} of {m['dynamic_count']} dynamic); "
                 f"undefined ('-') for static points and (near-)zero predictions")
    tw = m["threeway_epe"]
    groups = ("foreground_dynamic", "foreground_static", "background", "mean")
    lines += ["", "three-way EPE (m): " + ", ".join(f"{k.replace('_', ' ')} {_fmt(tw[k])}" for k in groups)]
    lines += ["", f"{'class (AV2 2024)':<18}{'static EPE':>12}{'dyn. norm. EPE':>16}"]
    for c, dn in m["dynamic_normalized_epe"].items():
        lines.append(f"{c:<18}{_fmt(m['static_epe_per_class'][c]):>12}{_fmt(dn):>16}")
    lines.append(f"{'mean':<18}{_fmt(m['mean_static_epe']):>12}{_fmt(m['mean_dynamic_normalized_epe']):>16}")
    return "\n".join(lines)


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, float) and math.isnan(x):
        return None  # JSON has no NaN
    return x


# ----------------------------------------------------------------------------- run
def _category_map(args):
    """The --categories value: None, 'av2' or a mapping read from a JSON file."""
    spec = args.categories
    if spec is None:
        meta = Path(args.gt_dir) / "sequence.json"
        try:
            info = json.loads(meta.read_text()) if meta.is_file() else {}
        except (OSError, ValueError):
            info = {}
        return "av2" if isinstance(info, dict) and str(info.get("dataset", "")).lower() == "av2" else None
    if spec.lower() == "av2":
        return "av2"
    path = Path(spec)
    if not path.is_file():
        raise CLIError(f"--categories {spec}: not 'av2' and no such JSON file")
    try:
        cmap = json.loads(path.read_text())
    except ValueError as e:
        raise CLIError(f"--categories {spec}: not valid JSON ({e})") from None
    if not isinstance(cmap, dict):
        raise CLIError(f"--categories {spec}: expected a JSON object {{\"class id\": \"meta-class\" or null}}")
    return cmap


def _check_json_path(spec: str | None) -> Path | None:
    """--json FILE, checked before any work (a directory or a missing parent: CLIError)."""
    if not spec:
        return None
    from floxels_ext.output_paths import check_output_file

    return check_output_file(spec, "--json", "metrics.json")


def _is_simulated(gt_dir) -> bool:
    meta = Path(gt_dir) / "sequence.json"
    try:
        info = json.loads(meta.read_text()) if meta.is_file() else {}
    except (OSError, ValueError):
        return False
    return isinstance(info, dict) and str(info.get("generator", "")).startswith("floxels_ext.evaluation.sim")


def run(args) -> int:
    from floxels_ext.evaluation.metrics import evaluate_sequence
    from floxels_ext.evaluation.protocol import AV2_EVAL_BOX, resolve_category_map

    json_path = _check_json_path(args.json)
    cmap = _category_map(args)
    if cmap == "av2" and _is_simulated(args.gt_dir):
        raise CLIError(f"--categories av2: {args.gt_dir} is a 'floxels simulate' sequence, whose classes are the "
                       f"simulator's meta-classes (0 background, 1 car, 2 other vehicle, 3 pedestrian, 4 wheeled "
                       f"VRU), not Argoverse 2 categories (read as AV2 ids, cars would count as ANIMAL); "
                       f"leave --categories out")
    try:
        resolve_category_map(cmap)
    except (TypeError, ValueError) as e:
        raise CLIError(f"--categories: {e}") from None
    if args.no_eval_box:
        box = None
    elif args.eval_box is not None:
        if not (args.eval_box > 0 and math.isfinite(args.eval_box)):
            raise CLIError(f"--eval-box must be a positive number of metres, got {args.eval_box}")
        box = args.eval_box
    else:
        box = AV2_EVAL_BOX if cmap == "av2" else None
    info: dict = {}
    preds, frames = load_eval_pair(args.pred_dir, args.gt_dir, raw_classes=cmap is not None, frames=args.frames,
                                   all_points=args.all_points, info=info)
    try:
        m = evaluate_sequence(preds, frames, include_ground=args.include_ground, category_map=cmap, eval_box=box)
    except ValueError as e:  # e.g. a class id the map does not know
        raise CLIError(f"{args.gt_dir}: {e}") from None
    m.update(frames_scored=info["frames"], gt_frames=info["gt_frames"], scored_points=info["scored_points"],
             not_optimised_count=info["not_optimised"], frame_points=info["points"])
    print(format_metrics(m))
    if json_path is not None:
        from floxels_ext.output_paths import replace_atomically

        text = json.dumps(_jsonable(m), indent=2) + "\n"
        try:
            replace_atomically(json_path.with_name(f".{json_path.name}.{os.getpid()}.tmp"), json_path,
                               lambda t: t.write_text(text))
        except OSError as e:
            raise CLIError(f"cannot write --json {json_path}: {e}") from None
        print(f"\nwrote {json_path}")
    return 0
