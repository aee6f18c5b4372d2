"""``parproj paper``: paper 1 section 5 (Tables 2-6) and paper 2's checks, reproduced."""

from __future__ import annotations

import argparse
from typing import Any

from ...io.files import (
    integer,
)
from .common import report


def _fmt(v: float) -> str:
    return f"{v:+.3e}" if (v != 0 and (abs(v) < 1e-2 or abs(v) >= 1e4)) else f"{v:+.4f}"


def _print_paper(r: dict[str, Any]) -> None:
    paper = r["paper"]
    print(
        "Paper 1 section 5 reproduced (ours | paper). Layout: seed",
        r["layout"]["seed"],
        "centroid",
        [round(c, 2) for c in r["layout"]["centroid_m"]],
        "m",
    )
    print("\nTables 2 and 3 (printed digits compared cell by cell):")
    for c in r["tables23_vs_paper"]["cells"]:
        flag = "ok " if c["match"] else "BAD"
        print(
            f"  [{flag}] T{c['table']} {c['side']:5s} {c['cell']:9s} ours {_fmt(c['ours']):>12s}"
            f"  paper {c['printed']:>9s}  {c['how']}"
        )
    print("  all cells match:", r["tables23_vs_paper"]["all_match"])
    print("\nTable 4 (direct, navigation-derived A, space intersection of all 25 points), metres:")
    for mode in ("no_ptp", "ptp", "ptp_nominal_roll"):
        o = r["table4"][mode]
        p = paper["table4"].get(mode)
        ps = (
            (
                f"   paper {p['xy_mean_m']:.3f}+-{p['xy_std_m']:.3f}  {p['z_mean_m']:.3f}+-"
                f"{p['z_std_m']:.3f}"
            )
            if p
            else ""
        )
        print(
            f"  {mode:17s} xy {o['xy_mean_m']:+.3f}+-{o['xy_std_m']:.3f}  "
            f"z {o['z_mean_m']:+.3f}+-{o['z_std_m']:.3f}{ps}"
        )
    print("\nTable 5 (A1..A8 and roll from the 16 GCP):")
    for side in ("left", "right"):
        for mode, o in r["table5"][side].items():
            p = paper["table5"][side].get(mode)
            ps = f"  paper sigma0 {p['sigma0_px']:.2f} psi {p['psi_deg']:+.2f}" if p else ""
            print(
                f"  {side:5s} {mode:12s} sigma0 {o['sigma0_px']:.2f} px  psi {o['psi_deg']:+.2f}"
                f"  A5 {o['A'][4]:+.2e} A7 {o['A'][6]:+.2e} A8 {o['A'][7]:+.2e}{ps}"
            )
    print("\nTable 6 (space intersection with the GCP-estimated parameters), metres:")
    for name in ("gcp", "check"):
        for mode, o in r["table6"][name].items():
            p = paper["table6"][name].get(mode)
            ps = (
                (
                    f"   paper {p['xy_mean_m']:.3f}+-{p['xy_std_m']:.3f}  {p['z_mean_m']:.3f}+-"
                    f"{p['z_std_m']:.3f}"
                )
                if p
                else ""
            )
            print(
                f"  {name:5s} {mode:12s} xy {o['xy_mean_m']:+.3f}+-{o['xy_std_m']:.3f}  "
                f"z {o['z_mean_m']:+.3f}+-{o['z_std_m']:.3f}{ps}"
            )
    p2 = r["paper2"]
    print("\nPaper 2 normalization on this geometry:")
    print(
        f"  exact parallel data: max |y-parallax| {p2['exact_parallel_y_parallax_px_max']:.2e} px"
    )
    print(
        f"  rigorous scenes, Eq 8 estimates: |y-parallax| mean {p2['y_parallax_px']['mean']:.3f}"
        f" max {p2['y_parallax_px']['max']:.3f} px (paper 2, real IKONOS: 1.5-2.3 px mean)"
    )
    print(
        f"  x-parallax vs height: rms about a line {p2['x_parallax_line_rms_px']:.4f} px; slope "
        f"{p2['x_parallax_px_per_m']['fitted']:.5f} px/m "
        f"(model {p2['x_parallax_px_per_m']['model']:.5f})"
    )
    if "spread" in r:
        sp = r["spread"]
        print(f"\nSpread over {sp['n_sets']} random point sets (median [5%, 95%]):")
        for k, v in sp["stats"].items():
            print(f"  {k:40s} {v['median']:9.3f} [{v['p05']:9.3f}, {v['p95']:9.3f}]")


def run(args: argparse.Namespace) -> int:
    """``parproj paper``: reproduce paper 1 section 5 and paper 2's checks."""
    from ...eval.paper import reproduce

    result = reproduce(n_sets=args.sets, seed=args.seed)
    report(args.json, result, _print_paper)
    return 0 if result["tables23_vs_paper"]["all_match"] else 1


def add_parser(sub: Any) -> None:
    """Add ``parproj paper`` to the sub-command parsers ``sub``."""
    from ...eval.paper import SEED

    p = sub.add_parser("paper", help="reproduce paper 1 section 5 (Tables 2-6) and paper 2 checks")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument(
        "--sets",
        type=integer(0, 100_000),
        default=200,
        help="random point sets for the spread of Tables 4-6 (0 to skip; default 200)",
    )
    p.add_argument(
        "--seed", type=integer(0, 2**32 - 1), default=SEED, help=f"layout seed (default {SEED})"
    )
    p.set_defaults(func=run)
