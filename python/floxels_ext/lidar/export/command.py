"""``floxels export RUN --format FORMAT OUT``: the flow of a ``floxels run`` in another tool's
format (``--format av2-submission``: the Argoverse 2 scene flow challenge's files and zip;
``--format opensceneflow``: training pseudo-labels as OpenSceneFlow reads them)."""

from __future__ import annotations

import argparse

__all__ = ["add_parser", "run", "FORMATS"]

FORMATS = {
    "av2-submission": "Argoverse 2 scene flow challenge: OUT/<log_id>/<timestamp_ns>.feather for the sweeps and "
                      "points of --masks, and the zip the leaderboard takes (needs pyarrow: extra av2)",
    "opensceneflow": "pseudo-labels for training (DeFlow, SeFlow, ZeroFlow's distillation loss in "
                     "OpenSceneFlow): OUT/<scene_id>.h5 and index_total.pkl / index_flow.pkl (needs h5py: "
                     "extra opensceneflow)",
}


def add_parser(sub) -> None:
    import textwrap

    p = sub.add_parser("export", help="write a run's flow in another tool's format (AV2 challenge, training)",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Write the flow of a 'floxels run' OUT_DIR (RUN: one sequence, or a dataset "
                                   "run's tree) in another tool's format.\n\nformats:\n" +
                                   "\n".join(textwrap.fill(f"{k}: {v}", 92, initial_indent="  ",
                                                            subsequent_indent="      ") for k, v in FORMATS.items()))
    p.add_argument("run_dir", metavar="RUN", help="an OUT_DIR of 'floxels run'")
    p.add_argument("out", metavar="OUT", help="output directory (created)")
    p.add_argument("--format", required=True, choices=list(FORMATS), help="what to write (see above)")
    p.add_argument("--masks", metavar="MASKS.zip", help="av2-submission: the challenge's mask archive "
                   "(val-masks.zip or test-masks.zip: which sweeps and points are scored)")
    p.add_argument("--zip", metavar="FILE", help="av2-submission: where the zip goes (default OUT/submission.zip)")
    p.add_argument("--partial", action="store_true", help="av2-submission: export the sweeps of --masks that RUN "
                   "has, if it lacks some (the zip is then not a valid submission; said when written)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.export.run_frames import ExportError

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CLIError(f"OUT {out} exists and is not a directory")
    if args.format != "av2-submission":
        given = [o for o, v in (("--masks", args.masks), ("--zip", args.zip), ("--partial", args.partial)) if v]
        if given:
            raise CLIError(f"{', '.join(given)} only {'applies' if len(given) == 1 else 'apply'} to --format av2-submission")
    try:
        if args.format == "av2-submission":
            from floxels_ext.lidar.export.av2_submission import export_av2_submission

            if not args.masks:
                raise CLIError("--format av2-submission needs --masks MASKS.zip: the challenge's mask archive "
                               "(val-masks.zip / test-masks.zip) names the sweeps and points it scores")
            zip_path = None
            if args.zip:
                from floxels_ext.output_paths import check_output_file

                zip_path = check_output_file(args.zip, "--zip", "submission.zip")
            export_av2_submission(args.run_dir, out, args.masks, zip_path=zip_path, partial=args.partial,
                                  report=print)
        else:
            from floxels_ext.lidar.export.opensceneflow import export_opensceneflow

            export_opensceneflow(args.run_dir, out, report=print)
    except ExportError as e:
        raise CLIError(str(e)) from None
    except OSError as e:  # a full disk, a permission problem: named, no traceback
        raise CLIError(f"cannot write {out}: {e}") from None
    return 0
