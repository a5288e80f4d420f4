"""Measurements that chose the rope model: stretch, tunnelling, knot-pull, speed, flying knot.

The command line of the rope study (:mod:`flyknot_tools.rope_study`): :func:`main` prints the
comparison table of ``docs/rope-model.md``; ``python -m flyknot_tools.rope_study --help``
lists the options.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import mujoco

from flyknot_tools.rope_study.measures import (
    VARIANTS,
    Config,
    measure_shape_error,
    measure_variant,
    variant_config,
)


def format_row(r: dict) -> str:
    """One markdown table row of :func:`measure_variant`'s result."""
    f, p = r["fast"], r["pull"]
    knot = (
        "diverged"
        if f["diverged"]
        else f"{f.get('knot_end', '-')}"
        + (" (formed)" if f.get("knot_any") and f.get("knot_end") != "trefoil" else "")
    )
    return (
        f"| {r['rope']} | {r['variant']} | {f['wall_per_sim']:.3f} | "
        f"{100 * f['max_stretch']:.2f} | {100 * f['max_edge_strain']:.1f} | "
        f"{f['crossings']} | {knot} | {p['kept']}/{p['trials']} | {p['crossings']} |"
    )


TABLE_HEADER = (
    "| rope | variant | wall s / sim s | max stretch % | max edge strain % | crossings "
    "(fast) | knot at end (fast) | knot-pull kept | crossings (pull) |\n"
    "|---|---|---|---|---|---|---|---|---|"
)


def main(argv: Sequence[str] | None = None) -> None:
    """Print the comparison table of ``docs/rope-model.md`` (markdown), optionally as JSON."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--ropes", type=int, nargs="*", default=[1, 4, 5, 6])
    ap.add_argument(
        "--variants",
        nargs="*",
        default=list(VARIANTS),
        choices=list(VARIANTS),
        metavar="NAME",
        help=f"any of: {', '.join(VARIANTS)}",
    )
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    ap.add_argument(
        "--shape",
        action="store_true",
        help="also print marker deviations from a 60-segment, 0.5 ms reference",
    )
    args = ap.parse_args(argv)
    seen: dict[str, int] = {}

    def count_warning(msg: str) -> None:
        key = msg.split(". Time =")[0].strip()
        seen[key] = seen.get(key, 0) + 1

    mujoco.set_mju_user_warning(count_warning)
    rows = []
    print(TABLE_HEADER, flush=True)
    for rope in args.ropes:
        for name in args.variants:
            r = measure_variant(rope, name)
            rows.append(r)
            print(format_row(r), flush=True)
    if args.shape:
        ref = Config(rope=1, segments=60, timestep=0.0005)
        for name in ("chosen", "40 segments", "20 segments", "dt 2 ms"):
            e = measure_shape_error(variant_config(1, VARIANTS[name]), ref)
            print(
                f"shape error rope 1 {name}: rms {1e3 * e['rms']:.1f} mm, "
                f"max {1e3 * e['max']:.1f} mm",
                flush=True,
            )
            rows.append({"shape": name, **e})
    for msg, k in sorted(seen.items()):
        print(f"MuJoCo warning x{k}: {msg}")
    if args.json is not None:
        import json

        args.json.write_text(json.dumps(rows, indent=1, default=float))
