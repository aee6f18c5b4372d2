"""``parproj replay``: a bag published into the live ROS 2 graph."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from ...io.files import (
    InputError,
    input_path,
    number,
)

#: Largest wait between two messages ``parproj replay`` accepts without --max-gap, s.
MAX_REPLAY_IDLE_S = 3600.0


def run(args: argparse.Namespace) -> int:
    """``parproj replay``: publish a bag into the live graph."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from ...ros.bag import BagReader
    from ...ros.live import largest_idle_s, replay

    args.inputs = [args.bag]
    bag = input_path(args.bag, "bag")
    reader = BagReader(bag)
    unknown = [t for t in args.wait_for if t not in reader.topics()]
    if unknown:
        raise InputError(
            "--wait-for", f"{unknown[0]} is not a topic of {bag} ({', '.join(reader.topics())})"
        )
    if args.rate > 0:
        idle, where = largest_idle_s(reader, args.max_gap)
        if idle / args.rate > MAX_REPLAY_IDLE_S:
            raise InputError(
                bag,
                f"log time jumps ahead by {idle:.6g} s at message {where} (a clock jump?): "
                f"more than {MAX_REPLAY_IDLE_S:g} s of waiting; shorten it with --max-gap S, "
                "or replay unpaced with --rate 0",
            )
    print(f"replay {bag}: rate {args.rate:g}" + (" (unpaced)" if args.rate == 0 else ""))
    sys.stdout.flush()
    # Our own SIGINT/SIGTERM handlers (main) stop the replay at once; rclpy's would not.
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = rclpy.create_node("parproj_replay")
        try:
            res = replay(
                node,
                bag,
                rate=args.rate,
                max_gap_s=args.max_gap,
                wait_for=args.wait_for,
                progress=not args.quiet,
            )
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    rec = res["recovery"]
    print(
        f"published {res['sent']} messages in {res['seconds']:.1f} s"
        + ("" if rec.complete else f"; bag cut off: {rec.error}")
    )
    return 0


def add_parser(sub: Any) -> None:
    """Add ``parproj replay`` to the sub-command parsers ``sub``."""
    p = sub.add_parser("replay", help="publish a bag into the live ROS 2 graph")
    p.add_argument("bag")
    p.add_argument("--rate", type=number(0.0, 1e6), default=1.0, help="speed factor (0 = unpaced)")
    p.add_argument(
        "--max-gap",
        type=number(0.0, 1e9, lo_open=True),
        default=None,
        help="shorten idle stretches longer than this many seconds",
    )
    p.add_argument("--wait-for", nargs="*", default=[], help="topics to wait subscribers on")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
