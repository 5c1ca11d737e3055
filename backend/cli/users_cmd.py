"""``mosaic-afm users``: the users of the multi-user mode (``MOSAIC_AUTH=users``), kept in
the data directory's database. Passwords are read from standard input, never from the
command line (which other users of the host can see). Each change is in the audit trail."""

from __future__ import annotations

import argparse
import getpass
import sys
from pathlib import Path
from typing import Any

from backend.cli.common import UsageError

ROLES = ("observer", "operator", "admin")


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "users",
        help="add, list, disable users of the multi-user mode",
        description="Users of the multi-user mode (MOSAIC_AUTH=users). A password is read from "
        "standard input (its first line), or asked for twice at a terminal.",
    )
    p.add_argument("--data-dir", default=None, help="the data directory (default MOSAIC_DATA_DIR)")
    verbs = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    add = verbs.add_parser("add", help="add a user (password from stdin)")
    add.add_argument("name")
    add.add_argument("--role", required=True, choices=ROLES)
    add.add_argument("--pam", action="store_true", help="logs in by the host's PAM, no password")
    verbs.add_parser("list", help="list the users")
    for verb, what in (
        ("disable", "disable a user: their sessions and keys end"),
        ("enable", "enable a disabled user"),
        ("passwd", "set a local user's password (from stdin)"),
    ):
        v = verbs.add_parser(verb, help=what)
        v.add_argument("name")
    role = verbs.add_parser("role", help="change a user's role")
    role.add_argument("name")
    role.add_argument("role", choices=ROLES)
    p.set_defaults(func=run_users)


def read_password() -> str:
    """The password: asked twice at a terminal, else the first line of standard input."""
    if sys.stdin.isatty():
        first = getpass.getpass("password: ")
        if getpass.getpass("again: ") != first:
            raise UsageError("the two passwords differ")
        return first
    return sys.stdin.readline().rstrip("\r\n")


def run_users(args: argparse.Namespace) -> int:
    from sqlalchemy import select

    from backend.db.access_models import User
    from backend.db.session import make_engine, migrate, session_factory
    from backend.security import audit
    from backend.security.authority import add_user, end_sessions
    from backend.security.passwords import hash_password
    from backend.settings import Settings

    settings = Settings(data_dir=Path(args.data_dir)) if args.data_dir else Settings()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    migrate(settings.database)
    sessions = session_factory(make_engine(settings.database), data_dir=settings.data_dir)
    me = f"{getpass.getuser()} (cli)"

    def log(action: str, name: str) -> None:
        target = f"users {args.verb} {name}"
        audit.record(
            sessions,
            user=me,
            address="cli",
            action=action,
            target=target,
            run_id=None,
            status=200,
            detail={},
        )

    if args.verb == "list":
        with sessions() as s:
            users = s.scalars(select(User).order_by(User.name)).all()
            if not users:
                print("no users (add one: mosaic-afm users add NAME --role admin)")
            for u in users:
                state = "disabled" if u.disabled else "active"
                print(f"{u.name:<24} {u.role:<9} {u.provider:<6} {state}")
        return 0
    if args.verb == "add":
        password = None if args.pam else read_password()
        try:
            add_user(
                sessions, args.name, args.role, password, provider="pam" if args.pam else "local"
            )
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        log("add_user", args.name)
        print(f"added {args.name} ({args.role}, {'pam' if args.pam else 'local'} login)")
        return 0
    with sessions() as s:
        user = s.scalar(select(User).where(User.name == args.name))
        if user is None:
            raise UsageError(f"no user {args.name!r} (list them: mosaic-afm users list)")
        if args.verb == "passwd":
            if user.provider != "local":
                raise UsageError(f"{args.name} logs in by PAM: change the password on the host")
            try:
                user.password_hash = hash_password(read_password())
            except ValueError as exc:
                raise UsageError(str(exc)) from None
        elif args.verb == "role":
            user.role = args.role
        else:
            user.disabled = args.verb == "disable"
        if args.verb in ("disable", "passwd"):  # every session of theirs ends
            end_sessions(s, user.id)
        s.commit()
    log(f"{args.verb}_user", args.name)
    print(f"{args.verb}: {args.name} done (a running server sees it within seconds)")
    return 0
