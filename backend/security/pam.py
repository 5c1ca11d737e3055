"""Log in by the host's PAM (Linux-PAM through ctypes): ``pam_authenticate`` then
``pam_acct_mgmt`` on a service, the password given to every prompt that hides its echo.

``confdir`` is a PAM configuration directory other than ``/etc/pam.d``
(``pam_start_confdir``, Linux-PAM 1.4 and later): a lab may give the server a service of its
own, and the tests a stack that runs a real module.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from pathlib import Path

PAM_SUCCESS = 0
PAM_PROMPT_ECHO_OFF = 1
PAM_PROMPT_ECHO_ON = 2
PAM_BUF_ERR = 5
PAM_CONV_ERR = 19


class _Message(ctypes.Structure):
    _fields_ = [("msg_style", ctypes.c_int), ("msg", ctypes.c_char_p)]


class _Response(ctypes.Structure):
    _fields_ = [("resp", ctypes.c_void_p), ("resp_retcode", ctypes.c_int)]


_CONV = ctypes.CFUNCTYPE(
    ctypes.c_int,
    ctypes.c_int,
    ctypes.POINTER(ctypes.POINTER(_Message)),
    ctypes.POINTER(ctypes.POINTER(_Response)),
    ctypes.c_void_p,
)


class _Conv(ctypes.Structure):
    _fields_ = [("conv", _CONV), ("appdata_ptr", ctypes.c_void_p)]


class PamUnavailable(RuntimeError):
    """No libpam on this host (or too old for a configuration directory)."""


def _libraries() -> tuple[ctypes.CDLL, ctypes.CDLL]:
    pam_name = ctypes.util.find_library("pam") or "libpam.so.0"
    libc_name = ctypes.util.find_library("c") or "libc.so.6"
    try:
        return ctypes.CDLL(pam_name), ctypes.CDLL(libc_name)
    except OSError as exc:
        raise PamUnavailable(f"PAM is not available on this host: {exc}") from None


def pam_login(
    user: str, password: str, *, service: str = "login", confdir: Path | None = None
) -> tuple[bool, str]:
    """Whether PAM's ``service`` lets ``user`` in with ``password``, and PAM's word for it."""
    pam, libc = _libraries()
    libc.calloc.restype = ctypes.c_void_p
    libc.calloc.argtypes = [ctypes.c_size_t, ctypes.c_size_t]
    libc.strdup.restype = ctypes.c_void_p
    libc.strdup.argtypes = [ctypes.c_char_p]
    pam.pam_strerror.restype = ctypes.c_char_p
    pam.pam_strerror.argtypes = [ctypes.c_void_p, ctypes.c_int]
    secret = password.encode()

    @_CONV
    def converse(n, messages, responses, _data):  # type: ignore[no-untyped-def]
        block = libc.calloc(n, ctypes.sizeof(_Response))
        if not block:
            return PAM_BUF_ERR
        answers = ctypes.cast(block, ctypes.POINTER(_Response))
        for i in range(n):
            style = messages[i].contents.msg_style
            if style in (PAM_PROMPT_ECHO_OFF, PAM_PROMPT_ECHO_ON):
                answers[i].resp = libc.strdup(secret if style == PAM_PROMPT_ECHO_OFF else b"")
        responses[0] = answers
        return PAM_SUCCESS

    handle = ctypes.c_void_p()
    conv = _Conv(converse, None)
    if confdir is not None:
        if not hasattr(pam, "pam_start_confdir"):
            raise PamUnavailable("this host's PAM has no pam_start_confdir (Linux-PAM < 1.4)")
        code = pam.pam_start_confdir(
            service.encode(),
            user.encode(),
            ctypes.byref(conv),
            str(confdir).encode(),
            ctypes.byref(handle),
        )
    else:
        code = pam.pam_start(
            service.encode(), user.encode(), ctypes.byref(conv), ctypes.byref(handle)
        )
    if code != PAM_SUCCESS:
        return False, f"PAM could not start the service {service!r} (code {code})"
    try:
        code = pam.pam_authenticate(handle, 0)
        if code == PAM_SUCCESS:
            code = pam.pam_acct_mgmt(handle, 0)
        said = (pam.pam_strerror(handle, code) or b"").decode(errors="replace")
        return code == PAM_SUCCESS, said
    finally:
        pam.pam_end(handle, code)
