"""``rigbuild edit``: spacetime editing of a weight-curve file (Seol et al. 2012, sec. 6).

    rigbuild edit weights.csv --frame 68 --set jawOpen=0.8 --set eyeBlink_L=1 --range 63 74 --out new.csv
    rigbuild edit weights.csv --frame 68 --from-csv pose.csv --range 63 74 --out new.csv --system system.npz

``--system`` (the ``system.npz`` the retarget_seol stage writes next to the curves) makes the edit
match the source marker movement with the prior, as in the paper; without it the edit preserves the
previous curves' own movement. ``--from-csv`` takes the new weights from a CSV with a header of shape
names (optionally ``frame,time,`` first): the row whose ``frame`` equals ``--frame``, or its only row.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from rigbuild.errors import InputError


def add_edit_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``edit`` on an argparse subparsers object; returns the parser."""
    p = subparsers.add_parser("edit", help="spacetime editing of a weight-curve CSV (Seol et al. 2012)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("weights", help="weight-curve CSV (frame,time,<shape>...)")
    p.add_argument("--frame", type=int, required=True, help="the edited frame")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--set", action="append", metavar="NAME=VALUE", help="new weight of a shape (repeatable)")
    src.add_argument("--from-csv", metavar="CSV", help="take the new weights from this CSV")
    p.add_argument("--range", type=int, nargs=2, required=True, metavar=("A", "B"),
                   help="propagation range; frames A and B keep their previous values")
    p.add_argument("--out", required=True, help="output CSV (or .json) for the new curves")
    p.add_argument("--system", help="system.npz of the retarget_seol stage (source-movement matching)")
    return p


def parse_set_values(items: list[str]) -> dict[str, float]:
    """``["jawOpen=0.8", ...]`` -> ``{"jawOpen": 0.8}``; malformed items raise :class:`InputError`."""
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise InputError(f"--set '{item}' is not NAME=VALUE", fix="write e.g. --set jawOpen=0.8")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise InputError(f"--set '{item}': '{value}' is not a number", fix="write e.g. --set jawOpen=0.8") from None
    return out


def read_pose_csv(path: str | Path, frame: int) -> dict[str, float]:
    """New weights from a CSV: header of shape names (``frame``/``time`` columns allowed)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("pose CSV not found", path=path)
    header = path.read_text(encoding="utf-8").splitlines()[0].strip().split(",")
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as exc:
        raise InputError(f"cannot read the pose CSV ({exc})", path=path, fix="numbers only below the header") from None
    if data.shape[1] != len(header):
        raise InputError(f"{len(header)} header names but {data.shape[1]} columns", path=path)
    if "frame" in header:
        rows = np.flatnonzero(data[:, header.index("frame")] == frame)
        if rows.size == 0 and data.shape[0] != 1:
            raise InputError(f"no row for frame {frame}", path=path, fix=f"add a row with frame = {frame}")
        row = data[rows[0]] if rows.size else data[0]
    elif data.shape[0] == 1:
        row = data[0]
    else:
        raise InputError(f"{data.shape[0]} rows and no 'frame' column", path=path,
                         fix="give one row, or a 'frame' column to pick the row")
    return {n: float(v) for n, v in zip(header, row) if n not in ("frame", "time")}


def run_edit(args: argparse.Namespace) -> int:
    from rigbuild.io.curves import read_weight_curves_csv, write_weight_curves_csv, write_weight_curves_json
    from rigbuild.retarget.editing import edit_spacetime
    from rigbuild.retarget.seol import SeolSystem

    src = Path(args.weights)
    if not src.is_file():
        raise InputError("weight-curve file not found", path=src)
    try:
        W, names, times = read_weight_curves_csv(src)
    except (ValueError, IndexError) as exc:
        raise InputError(f"not a weight-curve CSV ({exc})", path=src, fix="header frame,time,<shape>... then numbers") from None
    fps = 1.0 / float(np.median(np.diff(times))) if times.size > 1 and np.all(np.diff(times) > 0) else 30.0
    values = parse_set_values(args.set) if args.set else read_pose_csv(args.from_csv, args.frame)
    system = SeolSystem.load(args.system) if args.system else None
    W_new = edit_spacetime(W, args.frame, values, args.range, shape_names=names, system=system)
    out = Path(args.out)
    if out.suffix.lower() == ".json":
        write_weight_curves_json(out, W_new, names, fps, meta={"edited_from": str(src), "frame": args.frame,
                                                              "range": list(args.range), "set": values})
    else:
        write_weight_curves_csv(out, W_new, names, fps)
    changed = np.flatnonzero(np.abs(W_new - W).max(1) > 0)
    span = f"frames {changed.min()}-{changed.max()}" if changed.size else "no frame"
    print(f"edited frame {args.frame} ({len(values)} shapes), range [{args.range[0]}, {args.range[1]}]: "
          f"{span} changed; wrote {out}")
    return 0
