"""PAM logins through a real Linux-PAM stack: a configuration directory of the test's own
whose ``auth`` is ``pam_exec`` running a script that checks the password it is handed."""

from __future__ import annotations

from pathlib import Path

import pytest

from backend.security.pam import pam_login

MODULE = Path("/usr/lib/x86_64-linux-gnu/security/pam_exec.so")
pytestmark = pytest.mark.skipif(not MODULE.exists(), reason="no pam_exec module on this host")


def write_confdir(tmp_path: Path) -> Path:
    """A PAM configuration directory with the service ``mosaic``: carol, "tip-and-sample"."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    check = tmp_path / "check.sh"
    check.write_text(
        '#!/bin/sh\nread -r pw\n[ "$PAM_USER" = carol ] && [ "$pw" = "tip-and-sample" ]\n'
    )
    check.chmod(0o700)
    conf = tmp_path / "pam.d"
    conf.mkdir()
    (conf / "mosaic").write_text(
        f"auth required pam_exec.so expose_authtok quiet {check}\naccount required pam_permit.so\n"
    )
    return conf


@pytest.fixture
def confdir(tmp_path: Path) -> Path:
    return write_confdir(tmp_path)


def test_pam_lets_in_the_right_password_only(confdir: Path) -> None:
    assert pam_login("carol", "tip-and-sample", service="mosaic", confdir=confdir)[0]
    assert not pam_login("carol", "tip-and-samplE", service="mosaic", confdir=confdir)[0]
    assert not pam_login("dave", "tip-and-sample", service="mosaic", confdir=confdir)[0]


def test_a_service_pam_does_not_know_is_a_refusal_not_a_crash(confdir: Path) -> None:
    ok, said = pam_login("carol", "tip-and-sample", service="nothing-here", confdir=confdir)
    assert not ok
    assert "nothing-here" in said
