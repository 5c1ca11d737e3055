"""The multi-user mode on the real app: every route against every role (generated from the
route table), logins and their throttle, keys, CSRF, the operator lock and the audit trail."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.routing import APIRoute

from backend.api.access import ROUTES, RouteTable
from backend.api.app import api_routes
from backend.db.session import make_engine, migrate, session_factory
from backend.security import scopes as sc
from backend.security.authority import NoUsers, add_user
from backend.settings import Settings
from tests.backend.api.conftest import Server, open_server, plan

PASSWORD = "correct horse battery"
#: name -> role of the users every test here starts with
PEOPLE = {"alice": "admin", "olga": "operator", "oscar": "operator", "otto": "observer"}


def add_people(data_dir: Path) -> None:
    url = Settings(data_dir=data_dir).database
    migrate(url)
    sessions = session_factory(make_engine(url))
    for name, role in PEOPLE.items():
        add_user(sessions, name, role, PASSWORD, provider="local")


def users_server(tmp_path: Path, **settings: Any) -> Iterator[Server]:
    add_people(tmp_path)
    yield from open_server(tmp_path, auth="users", **settings)


@pytest.fixture
def multi(tmp_path: Path) -> Iterator[Server]:
    yield from users_server(tmp_path)


def login(server: Server, name: str, **extra: Any) -> dict[str, Any]:
    r = server.client.post(
        "/api/auth/login", json={"username": name, "password": PASSWORD, **extra}
    )
    assert r.status_code == 200, r.text
    body: dict[str, Any] = r.json()
    return body


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def as_user(server: Server, name: str) -> dict[str, str]:
    return bearer(login(server, name)["access_token"])


def audit_rows(server: Server, **query: Any) -> list[dict[str, Any]]:
    r = server.client.get("/api/audit", params=query, headers=as_user(server, "alice"))
    assert r.status_code == 200, r.text
    rows: list[dict[str, Any]] = r.json()
    return rows


# -- the route table -------------------------------------------------------------------------


def test_the_route_table_names_every_route_and_nothing_else() -> None:
    assert {(m, r.path) for r in api_routes() for m in r.methods} == set(ROUTES)


def test_a_route_missing_from_the_table_stops_the_app() -> None:
    def new_route() -> None: ...

    extra = APIRoute("/api/new-thing", new_route, methods=["POST"])
    with pytest.raises(ValueError, match="POST /api/new-thing is not in the route table"):
        RouteTable([*api_routes(), extra], ROUTES)


def _concrete(path: str) -> str:
    return re.sub(r"\{(\w+)\}", lambda m: {"fmt": "tif", "name": "nobody"}.get(m[1], "999"), path)


def _call(server: Server, method: str, path: str, headers: dict[str, str]) -> int:
    url = _concrete(path) + ("?follow=false" if path == "/api/events" else "")
    if method == "GET":
        return server.client.get(url, headers=headers).status_code
    # a body no route takes: a route reached answers 422 (or 404 for what does not exist),
    # nothing is changed, and the gate's answer (401, 403) is what is tested
    return server.client.request(method, url, json=[], headers=headers).status_code


def test_every_route_against_every_role(multi: Server) -> None:
    """Generated from the route table: a role with the route's scope gets through the gate,
    one without gets 403, nobody gets 401 (users mode, no anonymous reading)."""
    tokens = {name: login(multi, name)["access_token"] for name in PEOPLE}
    wrong: list[str] = []
    for (method, path), access in sorted(ROUTES.items()):
        for name, role in [*PEOPLE.items(), ("nobody", None)]:
            headers = bearer(tokens[name]) if role else {}
            status = _call(multi, method, path, headers)
            if path == "/api/auth/logout" and role:  # that session ended: a new one
                tokens[name] = login(multi, name)["access_token"]
            if access.scope is None:
                expected = "through"
            elif role is None:
                expected = "401"
            else:
                expected = "through" if access.scope in sc.ROLES[role] else "403"
            got = "through" if status not in (401, 403) else str(status)
            if got != expected:
                wrong.append(f"{method} {path} as {name} ({role}): {status}, not {expected}")
    assert not wrong, "\n".join(wrong)


def test_anonymous_reading_when_switched_on(tmp_path: Path) -> None:
    for server in users_server(tmp_path, anonymous_read=True):
        assert server.client.get("/api/runs").status_code == 200
        assert server.client.get("/api/lock").status_code == 200
        assert server.client.post("/api/runs", json=plan()).status_code == 401
        assert server.client.get("/api/audit").status_code == 401
        assert server.client.post("/api/instrument/viewer/session").status_code == 401


def test_the_users_mode_needs_a_user_to_start(tmp_path: Path) -> None:
    with pytest.raises(NoUsers, match="mosaic-afm users add NAME --role admin"):
        list(open_server(tmp_path, auth="users"))


# -- logins, sessions, throttle, CSRF --------------------------------------------------------


def test_login_refresh_logout(multi: Server) -> None:
    tokens = login(multi, "olga")
    assert set(tokens) >= {"access_token", "refresh_token", "expires_in"}
    who = multi.client.get("/api/auth/whoami", headers=bearer(tokens["access_token"])).json()
    assert (who["user"], who["role"], who["via"], who["mode"]) == (
        "olga",
        "operator",
        "session",
        "users",
    )
    again = multi.client.post("/api/auth/refresh", json={"refresh_token": tokens["refresh_token"]})
    assert again.status_code == 200
    # the refresh token is replaced: the old one is refused from now on
    old = multi.client.post("/api/auth/refresh", json={"refresh_token": tokens["refresh_token"]})
    assert old.status_code == 401
    fresh = again.json()
    assert (
        multi.client.post("/api/auth/logout", headers=bearer(fresh["access_token"])).status_code
        == 204
    )
    assert multi.client.get("/api/runs", headers=bearer(fresh["access_token"])).status_code == 401
    gone = multi.client.post("/api/auth/refresh", json={"refresh_token": fresh["refresh_token"]})
    assert gone.status_code == 401


def test_an_expired_or_forged_access_token_is_refused(tmp_path: Path) -> None:
    for server in users_server(tmp_path, access_ttl=30):
        token = login(server, "otto")["access_token"]
        head, sid, expiry, sig = token.split(".")
        forged = f"{head}.{sid}.{int(expiry) + 3600}.{sig}"
        assert server.client.get("/api/runs", headers=bearer(forged)).status_code == 401
        assert server.client.get("/api/runs", headers=bearer(token)).status_code == 200


def test_failed_logins_are_throttled_and_audited(tmp_path: Path) -> None:
    for server in users_server(tmp_path, login_attempts=3):
        for _ in range(3):
            r = server.client.post("/api/auth/login", json={"username": "olga", "password": "no"})
            assert r.status_code == 401
            assert r.json()["detail"] == "wrong user name or password"
        r = server.client.post("/api/auth/login", json={"username": "olga", "password": PASSWORD})
        assert r.status_code == 429
        assert int(r.headers["Retry-After"]) > 0
        # the address is held too: another name from it waits as well
        r = server.client.post("/api/auth/login", json={"username": "otto", "password": PASSWORD})
        assert r.status_code == 429
        server.services.authority.throttle.succeeded("address:testclient", "name:olga")
        rows = audit_rows(server, action="login")
        outcomes = [(r["user"], r["outcome"], r["status"]) for r in reversed(rows)]
        assert outcomes[:5] == [("olga", "refused", 401)] * 3 + [
            ("olga", "refused", 429),
            ("otto", "refused", 429),
        ]


def test_the_browser_session_needs_its_csrf_header_for_changes(multi: Server) -> None:
    csrf = login(multi, "olga", cookie=True)["csrf_token"]
    client = multi.client
    assert client.cookies.get("mosaic_access")
    assert client.get("/api/runs").status_code == 200  # reads: the cookie alone
    refused = client.post("/api/runs", json=plan())
    assert refused.status_code == 403
    assert "X-CSRF-Token" in refused.json()["detail"]
    assert (
        client.post("/api/runs", json=plan(), headers={"X-CSRF-Token": "x" * 43}).status_code == 403
    )
    made = client.post("/api/runs", json=plan(), headers={"X-CSRF-Token": csrf})
    assert made.status_code == 201
    assert made.json()["created_by"] == "olga"
    # the refresh cookie, without the header, refreshes nothing
    assert client.post("/api/auth/refresh").status_code == 401
    assert client.post("/api/auth/refresh", headers={"X-CSRF-Token": csrf}).status_code == 200


# -- keys ------------------------------------------------------------------------------------


def test_a_key_acts_for_its_user_within_its_scopes_until_revoked(multi: Server) -> None:
    olga = as_user(multi, "olga")
    made = multi.client.post(
        "/api/keys", json={"scopes": ["read", "runs"], "note": "nightly"}, headers=olga
    )
    assert made.status_code == 201, made.text
    key, key_id = made.json()["key"], made.json()["id"]
    run = multi.client.post("/api/runs", json=plan(), headers=bearer(key))
    assert run.status_code == 201
    assert run.json()["created_by"] == "olga"
    # a key cannot merge (not in its scopes), nor make keys
    merge = multi.client.post("/api/runs/1/merges", json={}, headers=bearer(key))
    assert merge.status_code == 403
    assert "API key" in merge.json()["detail"]
    assert (
        multi.client.post("/api/keys", json={"scopes": ["read"]}, headers=bearer(key)).status_code
        == 403
    )
    listed = multi.client.get("/api/keys", headers=olga).json()
    assert [k["prefix"] for k in listed] == [made.json()["prefix"]]
    assert key not in str(listed)
    assert multi.client.delete(f"/api/keys/{key_id}", headers=olga).status_code == 204
    # refused at its very next request (no grace period)
    assert multi.client.get("/api/runs", headers=bearer(key)).status_code == 401


def test_a_key_holds_only_its_users_scopes_and_expires(multi: Server) -> None:
    otto = as_user(multi, "otto")
    beyond = multi.client.post("/api/keys", json={"scopes": ["read", "runs"]}, headers=otto)
    assert beyond.status_code == 403
    assert "runs" in beyond.json()["detail"]
    short = multi.client.post("/api/keys", json={"scopes": ["read"], "expires_in": 1}, headers=otto)
    key = short.json()["key"]
    assert multi.client.get("/api/runs", headers=bearer(key)).status_code == 200
    time.sleep(1.2)
    assert multi.client.get("/api/runs", headers=bearer(key)).status_code == 401


def test_a_disabled_user_is_refused_at_once(multi: Server) -> None:
    otto = as_user(multi, "otto")
    assert multi.client.get("/api/runs", headers=otto).status_code == 200
    assert (
        multi.client.delete("/api/users/otto", headers=as_user(multi, "alice")).status_code == 204
    )
    assert multi.client.get("/api/runs", headers=otto).status_code == 401
    r = multi.client.post("/api/auth/login", json={"username": "otto", "password": PASSWORD})
    assert r.status_code == 401


# -- the operator lock -----------------------------------------------------------------------


def test_two_operators_and_the_lock(multi: Server) -> None:
    olga, oscar, alice = (as_user(multi, n) for n in ("olga", "oscar", "alice"))
    taken = multi.client.post(
        "/api/lock", json={"note": "overnight run on sample 12"}, headers=olga
    )
    assert taken.status_code == 200
    seen = multi.client.get("/api/lock", headers=as_user(multi, "otto")).json()
    assert (seen["holder"], seen["note"], seen["yours"]) == (
        "olga",
        "overnight run on sample 12",
        False,
    )
    # another operator observes, and is refused every change of the instrument, by name
    assert multi.client.get("/api/runs", headers=oscar).status_code == 200
    refused = multi.client.post("/api/runs", json=plan(), headers=oscar)
    assert refused.status_code == 423
    assert "olga holds the instrument" in refused.json()["detail"]
    assert multi.client.post("/api/lock", json={}, headers=oscar).status_code == 423
    assert multi.client.request("DELETE", "/api/lock", json={}, headers=oscar).status_code == 423
    run = multi.client.post("/api/runs", json=plan(), headers=olga).json()
    assert multi.client.post(f"/api/runs/{run['id']}/start", headers=oscar).status_code == 423
    # an admin breaks it only with a reason, which is logged
    no_reason = multi.client.request("DELETE", "/api/lock", json={}, headers=alice)
    assert no_reason.status_code == 422
    broken = multi.client.request(
        "DELETE", "/api/lock", json={"reason": "olga is away, sample must come out"}, headers=alice
    )
    assert broken.status_code == 200
    row = audit_rows(multi, action="release_lock")[0]
    assert row["user"] == "alice"
    assert "olga is away" in row["detail"]["reason"]
    assert (
        multi.client.post("/api/lock", json={"note": "mine now"}, headers=oscar).status_code == 200
    )


def test_an_abort_by_another_operator_is_allowed_and_logged(multi: Server) -> None:
    olga, oscar = as_user(multi, "olga"), as_user(multi, "oscar")
    multi.client.post("/api/lock", json={"note": "long run"}, headers=olga)
    run = multi.client.post("/api/runs", json=plan(size=4e-6, pixels=(32, 32)), headers=olga).json()
    started = multi.client.post(f"/api/runs/{run['id']}/start", headers=olga)
    assert started.status_code == 202
    assert started.json()["started_by"] == "olga"
    aborted = multi.client.post(f"/api/runs/{run['id']}/abort", json={}, headers=oscar)
    assert aborted.status_code == 200, aborted.text
    multi.client.headers.update(as_user(multi, "otto"))  # the helper's reads
    multi.wait_state(run["id"], "aborted")
    row = audit_rows(multi, run=run["id"], action="abort_run")[0]
    assert (row["user"], row["outcome"]) == ("oscar", "ok")
    assert row["detail"]["note"] == "not the lock's holder (olga)"


# -- the audit trail -------------------------------------------------------------------------


def test_every_state_changing_route_leaves_an_audit_row(multi: Server) -> None:
    alice = as_user(multi, "alice")
    changes = sorted(k for k, a in ROUTES.items() if a.audit)
    assert len(changes) >= 25
    names = {(m, r.path): r.name for r in api_routes() for m in r.methods}
    missing = []
    for method, path in changes:
        if path == "/api/auth/logout":
            headers = bearer(login(multi, "alice")["access_token"])
        else:
            headers = alice
        status = _call(multi, method, path, headers)
        newest = audit_rows(multi, limit=2)
        # the newest row but the audit read's own login
        row = next(r for r in newest if not (r["action"] == "login" and r["status"] == 200))
        if (row["action"], row["target"], row["status"]) != (
            names[(method, path)],
            f"{method} {_concrete(path)}",
            status,
        ):
            missing.append(f"{method} {path}: {row}")
    assert not missing, "\n".join(missing)
    # reads leave none
    before = audit_rows(multi, limit=1000)
    multi.client.get("/api/runs", headers=alice)
    assert len(audit_rows(multi, limit=1000)) == len(before) + 1  # that read's own login


def test_secrets_never_reach_the_audit_events_or_answers(multi: Server, caplog: Any) -> None:
    tokens = login(multi, "olga")
    key = multi.client.post(
        "/api/keys", json={"scopes": ["read"]}, headers=bearer(tokens["access_token"])
    ).json()["key"]
    multi.client.post("/api/auth/login", json={"username": "olga", "password": "wrong one!"})
    trail = str(audit_rows(multi, limit=1000))
    events = multi.client.get("/api/events?follow=false", headers=bearer(key)).text
    for secret in (PASSWORD, "wrong one!", tokens["access_token"], tokens["refresh_token"], key):
        assert secret not in trail
        assert secret not in events
        assert secret not in caplog.text
    assert oct((multi.data_dir / "auth_secret").stat().st_mode & 0o777) == "0o600"
    assert oct((multi.data_dir / "mosaic.sqlite").stat().st_mode & 0o777) == "0o600"


@pytest.mark.skipif(
    not Path("/usr/lib/x86_64-linux-gnu/security/pam_exec.so").exists(), reason="no pam_exec"
)
def test_a_pam_user_logs_in_by_the_hosts_pam(tmp_path: Path) -> None:
    from tests.backend.security.test_pam import write_confdir

    conf = write_confdir(tmp_path / "pam")
    data = tmp_path / "data"
    add_people(data)
    add_user(
        session_factory(make_engine(Settings(data_dir=data).database)),
        "carol",
        "observer",
        None,
        provider="pam",
    )
    for server in open_server(data, auth="users", pam_service="mosaic", pam_confdir=conf):
        good = {"username": "carol", "password": "tip-and-sample"}
        r = server.client.post("/api/auth/login", json=good)
        assert r.status_code == 200, r.text
        who = server.client.get("/api/auth/whoami", headers=bearer(r.json()["access_token"]))
        assert (who.json()["user"], who.json()["role"]) == ("carol", "observer")
        bad = server.client.post("/api/auth/login", json={**good, "password": "tip-and-samplE"})
        assert bad.status_code == 401
