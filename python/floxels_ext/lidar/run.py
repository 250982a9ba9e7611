"""``floxels run INPUT --out OUT_DIR``: the command's options and where INPUT goes.

Every INPUT (one sequence, a dataset, any INPUT with ``--ray``) goes to
:func:`floxels_ext.lidar.dataset.run.run_input`, which runs its tasks through the one engine
(``lidar/dataset/``). Kept apart from it so that the command's options are read without
loading the engine, and so that the packages below import nothing upwards.
"""

from __future__ import annotations

__all__ = ["add_parser", "run"]


def _opt_float(text: str) -> float | None:
    if text.lower() in ("none", "off", "inf"):
        return None
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"expected a number or 'none', got {text!r}") from None
    return v


def add_parser(sub) -> None:
    import argparse
    import textwrap

    from floxels_ext.lidar.dataset.run import add_dataset_arguments

    def description() -> str:  # called when the help is printed (cli._Parser): io.outputs loads numpy
        from floxels_ext.lidar.io.outputs import OUTPUT

        return "\n\n".join(textwrap.fill(t, 92) for t in (
            "Estimate the flow of every frame of INPUT and write one .npz per frame to OUT_DIR.",
            "INPUT: a directory of frame files of one format (.bin .npy .npz .pcd .ply .feather, natural "
            "order), a 'floxels simulate' sequence, or an Argoverse 2 log directory "
            "(sensors/lidar/*.feather + city_SE3_egovehicle.feather).",
            "Ego-motion: --poses FILE, else poses stored with the frames (AV2, .npz 'pose'), else "
            "--odometry kiss-icp (estimated; pip install 'floxels_ext[odometry]'), else --no-ego-motion "
            "if the scans are already in one frame.")) + "\n\n" + OUTPUT

    p = sub.add_parser("run", help="estimate scene flow for a whole lidar sequence (resumable)",
                       formatter_class=argparse.RawDescriptionHelpFormatter, description=description)
    p.add_argument("input", metavar="INPUT", nargs="?")
    p.add_argument("--out", metavar="OUT_DIR", help="output directory (created; required)")
    p.add_argument("--poses", metavar="FILE", help="poses: KITTI poses.txt (12/line), 4x4 per line, TUM, "
                   ".npy/.npz (F,4,4), or AV2 city_SE3_egovehicle.feather")
    p.add_argument("--calib", metavar="FILE", help="KITTI calib.txt: turn camera poses into velodyne poses")
    p.add_argument("--odometry", choices=["kiss-icp"], help="estimate poses with KISS-ICP when none are given")
    p.add_argument("--no-ego-motion", action="store_true", help="the scans are already ego-motion compensated")
    p.add_argument("--method", default="floxels", help="scene-flow method (see --list-methods; default floxels)")
    p.add_argument("--list-methods", action="store_true", help="print the available methods and exit")
    p.add_argument("--scans", type=int, default=None,
                   help="scans per window, target in the middle (default: the preset's, paper 5, accurate 11)")
    p.add_argument("--preset", default=None,
                   help="Floxels settings: accurate (default; beyond the paper: 11 scans, motion evidence judged "
                        "where each scan could see, rigid refinement of moving clusters from their flow and their "
                        "searched velocity; docs/accurate.md) or paper (the paper's method, a faithful "
                        "reproduction; the API's default). Other --methods take no preset")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda if available)")
    p.add_argument("--frames", metavar="A:B", help="only these frames (Python slice over the sorted frames); "
                   "neighbours outside still serve as support scans")
    p.add_argument("--max-iters", type=int, help="shortcut for --option max_iters=N")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="method option (Floxels: any FloxelsConfig field, e.g. voxel_size=0.5); repeatable")
    p.add_argument("--raw-flow", action="store_true",
                   help="Floxels: keep the optimiser's flow of the groups of points whose motion the scans do "
                        "not support (default: set to 0, FloxelsConfig evidence=zero; with --preset paper the "
                        "output is then the paper's raw flow); the motion evidence is written either way "
                        "('evidence', 'explained': dynamic & explained are the default's moving points)")
    p.add_argument("--no-ground-removal", action="store_true", help="keep ground points")
    p.add_argument("--min-range", type=_opt_float, default=3.0, help="m, drop closer points (default 3; 'none')")
    p.add_argument("--max-range", type=_opt_float, default=50.0, help="m, drop farther points (default 50; 'none')")
    p.add_argument("--max-height", type=_opt_float, default=4.0,
                   help="m above the local ground, drop higher points (default 4; 'none')")
    p.add_argument("--ground-threshold", type=float, default=0.3, help="m above the ground surface that is "
                   "still ground (default 0.3)")
    p.add_argument("--ground-window", type=float, default=8.0, help="m, morphological window (default 8)")
    p.add_argument("--ground-cell", type=float, default=0.5, help="m, ground grid cell (default 0.5)")
    p.add_argument("--outlier-below", type=_opt_float, default=1.0,
                   help="m under the robust ground reference: deeper points are outliers (multipath), removed "
                   "and counted in the summary (default 1; 'none')")
    p.add_argument("--outlier-above", type=_opt_float, default=20.0,
                   help="m above the sensor: higher points are outliers (default 20; 'none')")
    p.add_argument("--bin-columns", type=int, choices=[3, 4, 5, 6], help="float32 columns of .bin frames "
                   "(default: from the file size; 4 KITTI, 5 nuScenes)")
    p.add_argument("--ext", help="frame extension to use when INPUT mixes formats")
    p.add_argument("--points-frame", choices=["auto", "sensor", "world"], default="auto",
                   help="coordinates of the stored points: each scan's sensor frame, or one world frame "
                        "(.npz with the sensor 'pose', as 'floxels simulate' writes); auto: world for a "
                        "'floxels simulate' directory (sequence.json present), else sensor")
    p.add_argument("--chunk", type=int, default=None, help="targets per method call (one re-centred world frame, "
                   "shared distance transforms); default 128")
    p.add_argument("--force", action="store_true", help="recompute frames already written (also those written "
                   "with other settings)")
    p.add_argument("--dynamic-threshold", type=float, default=0.05, metavar="M",
                   help="m per frame step: optimised points moving faster are flagged 'dynamic' (default 0.05, "
                        "0.5 m/s at 10 Hz as in the Argoverse 2 protocol)")
    p.add_argument("--self-contained", action="store_true", help="also store the input points in every output "
                   "(default: read back from the recorded source file)")
    p.add_argument("--compress", action="store_true", help="zip-compress the outputs (smaller, slower)")
    p.add_argument("--summary", metavar="FILE", help="JSON summary of the run (default OUT_DIR/run_summary.json)")
    p.add_argument("--workers", type=int, default=None, help="reader/preprocessor threads (default: the CPU "
                   "cores, at most 6)")
    p.add_argument("--writers", type=int, default=None, help="writer threads (default 2: an output is written "
                   "in ~5 ms, mostly without the GIL; up to 8 write what is left once the method is done)")
    p.add_argument("--worker-kind", choices=["auto", "thread", "process"], default="auto",
                   help="readers/preprocessors and writers as threads or processes (CPU preprocessing only); "
                        "auto: threads (faster than processes on the hosts measured)")
    p.add_argument("--preprocess-device", choices=["auto", "cpu", "cuda"], default="auto",
                   help="where cropping/ground removal run: the compiled CPU op, or torch on the GPU (same masks; "
                        "worker threads); auto: the CPU op (the faster on the hosts measured)")
    add_dataset_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    if args.list_methods:
        from floxels_ext.methods import available_methods, get_method

        for name in available_methods():
            print(f"{name:<12} {get_method(name).description}")
        return 0
    from floxels_ext.lidar.dataset.run import run_input

    return run_input(args)
