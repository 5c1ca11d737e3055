"""``mosaic-afm check`` and ``mosaic-afm backup``: a data directory's health and its copies."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from backend.cli.common import UsageError


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "check",
        help="verify a data directory: the database against the run files",
        description="Check the database's integrity, that every stored patch and merge result "
        "is readable in its run's file, and list run files nobody refers to. Read only; safe "
        "while the server runs. Exit 0 when healthy, 1 when something is wrong.",
    )
    p.add_argument("--data-dir", default="data", help="the data directory (default ./data)")
    p.set_defaults(func=run_check)
    p = sub.add_parser(
        "backup",
        help="copy a data directory consistently, also while the server runs",
        description="Copy the run files (each re-read until whole), then the database by "
        "SQLite's online backup, into DIR (new or empty). Paths inside are relative: serve "
        "the copy from anywhere with --data-dir DIR.",
    )
    p.add_argument("dir", help="where the copy goes (a new or empty folder)")
    p.add_argument("--data-dir", default="data", help="the data directory (default ./data)")
    p.set_defaults(func=run_backup)


def run_check(args: argparse.Namespace) -> int:
    from backend.db.maintenance import check_data_dir

    try:
        report = check_data_dir(Path(args.data_dir))
    except FileNotFoundError as exc:
        raise UsageError(str(exc)) from None
    for note in report.notes:
        print(note)
    for problem in report.problems:
        print(f"PROBLEM: {problem}")
    print("healthy" if report.ok else f"{len(report.problems)} problem(s) found")
    return 0 if report.ok else 1


def run_backup(args: argparse.Namespace) -> int:
    from backend.db.maintenance import backup_data_dir

    try:
        copied = backup_data_dir(Path(args.data_dir), Path(args.dir))
    except (FileNotFoundError, FileExistsError) as exc:
        raise UsageError(str(exc)) from None
    print(f"copied {len(copied)} files of {args.data_dir} to {args.dir}")
    return 0
