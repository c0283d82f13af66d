"""The ``rigbuild`` command line.

    rigbuild init-session <folder>     scaffold session.yaml from a folder of images and check it
    rigbuild synth <folder>            generate a synthetic session (config/config.yaml style block)
    rigbuild eval <session>            print the metrics table with pass/warn/fail
    rigbuild edit ...                  spacetime editing of a weight-curve file (Seol et al. 2012)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rigbuild.errors import RigbuildError


def _init_session(args: argparse.Namespace) -> int:
    from rigbuild.session_scaffold import scaffold_session

    from rigbuild.session_scaffold import check_board

    inverted = {"true": True, "false": False, "auto": "auto"}[args.inverted]
    charuco = {"marker_size_mm": args.marker_mm, "dictionary": args.dictionary, "legacy_pattern": args.legacy_pattern}
    spec, problems = scaffold_session(
        Path(args.folder),
        board={"type": args.board, "squares_x": args.squares[0], "squares_y": args.squares[1],
               "square_size_mm": args.square_mm, **(charuco if args.board == "charuco" else {}),
               **({"inverted": inverted} if inverted is not False else {})},
        fps=args.fps, template_rig=args.template_rig, force=args.force,
    )
    print(f"session '{spec.name}': {len(spec.cameras)} cameras {spec.cameras}, image {spec.width}x{spec.height}, "
          f"{len(spec.rom)} ROM sequences, {len(spec.performances)} performances")
    if args.board_check > 0:
        lines, board_problems = check_board(spec, args.board_check)
        print("\n".join(lines))
        problems = problems + board_problems
    for p in problems:
        print(f"  problem: {p}")
    print(f"wrote {Path(args.folder) / 'session.yaml'}" + (" (with problems)" if problems else ""))
    return 1 if problems else 0


def _synth(args: argparse.Namespace) -> int:
    import yaml

    from rigbuild.synth.session import generate_session

    block = yaml.safe_load(Path(args.config).read_text())["sessions"][args.name]["synthetic"] if args.config else {}
    generate_session(args.folder, args.name, block, progress=print)
    return 0


def _eval(args: argparse.Namespace) -> int:
    from rigbuild.io.metrics import read_metrics
    from rigbuild.report.table import format_metrics_table, format_summary

    path = Path(args.results) / args.session / "metrics.json"
    if not path.exists():
        print(f"{path}: no metrics yet (run snakemake first)", file=sys.stderr)
        return 1
    metrics = read_metrics(path)
    summary, _ = format_summary(metrics)
    table, n_fail = format_metrics_table(metrics)
    print(summary + "\n\n" + table)
    return 1 if (n_fail and args.strict) else 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rigbuild", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("init-session", help="scaffold and check session.yaml for a folder of images")
    p.add_argument("folder")
    p.add_argument("--board", choices=["charuco", "chessboard"], default="charuco")
    p.add_argument("--squares", type=int, nargs=2, default=[7, 5], metavar=("X", "Y"))
    p.add_argument("--square-mm", type=float, default=30.0)
    p.add_argument("--marker-mm", type=float, default=22.0)
    p.add_argument("--dictionary", default="DICT_5X5_100", help="any OpenCV predefined dictionary")
    p.add_argument("--inverted", choices=["false", "true", "auto"], default="false",
                   help="board printed inverted (white markers on black); auto tries both")
    p.add_argument("--legacy-pattern", action="store_true", help="ChArUco layout of OpenCV < 4.6")
    p.add_argument("--board-check", type=int, default=3, metavar="N",
                   help="detect the board in the first N calibration images per camera (0: skip)")
    p.add_argument("--fps", type=float, default=60.0)
    p.add_argument("--template-rig", default="procedural")
    p.add_argument("--force", action="store_true", help="overwrite an existing session.yaml")
    p.set_defaults(func=_init_session)

    p = sub.add_parser("synth", help="generate a synthetic session with ground truth")
    p.add_argument("folder")
    p.add_argument("--name", default="demo")
    p.add_argument("--config", help="a config YAML whose sessions.<name>.synthetic block to use")
    p.set_defaults(func=_synth)

    p = sub.add_parser("eval", help="print a session's metrics with pass/warn/fail")
    p.add_argument("session")
    p.add_argument("--results", default="results")
    p.add_argument("--strict", action="store_true", help="exit 1 when a metric fails")
    p.set_defaults(func=_eval)

    try:
        from rigbuild.cli_edit import add_edit_parser, run_edit

        add_edit_parser(sub).set_defaults(func=run_edit)
    except ImportError:  # pragma: no cover - the editing module is part of the package
        pass
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except RigbuildError as exc:
        print(f"rigbuild: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
