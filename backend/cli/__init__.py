"""``mosaic-afm``: the command line. Each subcommand imports what it needs only when it runs."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from backend.cli import (
    formats_cmd,
    merge_cmd,
    serve_cmd,
    sim_cmd,
    sim_nanonis_cmd,
    sim_scan_cmd,
    sim_sharksem_cmd,
    store_cmd,
    synth_cmd,
    users_cmd,
)
from backend.cli.common import UsageError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mosaic-afm",
        description="Long-range AFM by mosaics: acquire, merge and inspect overlapping patches.",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks of internal errors")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    merge_cmd.add_parser(sub)
    synth_cmd.add_parser(sub)
    sim_cmd.add_parser(sub)
    sim_nanonis_cmd.add_parser(sub)
    sim_sharksem_cmd.add_parser(sub)
    sim_scan_cmd.add_parser(sub)
    serve_cmd.add_parser(sub)
    formats_cmd.add_parsers(sub)
    store_cmd.add_parsers(sub)
    users_cmd.add_parsers(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit code (2 for bad input, 1 for an internal error)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse already printed usage and the error (or --help)
        return int(exc.code or 0)
    try:
        code: int = args.func(args)
        return code
    except UsageError as exc:
        print(f"mosaic-afm {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mosaic-afm {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # last resort: a message, not a traceback, unless asked for
        if args.debug:
            raise
        print(
            f"mosaic-afm {args.command}: internal error: {type(exc).__name__}: {exc} "
            "(run with --debug for the traceback and please report it)",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
