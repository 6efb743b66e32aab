"""The design page's port, checked before anything else: ``jaxcart app`` compiles for seconds
before it serves, and a busy port said after that is time lost. Standard library only, so the
command asks before jax or Bokeh is imported."""

from __future__ import annotations

import errno
import socket

from jaxcart.errors import UserError


def free_port(address: str) -> int:
    """A port the system has free on ``address`` now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((address, 0))
        return s.getsockname()[1]


def check_port(address: str, port: int) -> None:
    """Refuse, in one line with the fix, a port that ``jaxcart app`` cannot listen on (taken by
    another server, a second ``jaxcart app`` say) or an address this machine does not have.
    Asked before anything is computed: the region compiles for seconds first."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            # As tornado binds (SO_REUSEADDR): a port left in TIME_WAIT by an earlier page is
            # free for it, one that a server listens on is not. Port 0 checks the address.
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((address, port))
    except (socket.gaierror, UnicodeError) as exc:  # a name that does not resolve
        raise UserError(
            f"--address {address}: not an address of this machine ({exc}); give one such as "
            "127.0.0.1"
        ) from None
    except OSError as exc:
        raise UserError(port_problem(address, port, exc)) from None


def port_problem(address: str, port: int, exc: OSError) -> str:
    """The one line for a port or address that cannot be listened on, with the fix."""
    if exc.errno == errno.EADDRNOTAVAIL:
        return (
            f"--address {address}: not an address of this machine ({exc.strerror}); give one "
            "such as 127.0.0.1 (this machine only) or 0.0.0.0 (every network)"
        )
    if exc.errno == errno.EADDRINUSE:
        why = "another server listens there (a jaxcart app already running?)"
    else:
        why = exc.strerror or str(exc)
    return (
        f"--port {port}: cannot listen on {address}:{port} ({why}); give another port "
        "(--port 0 picks a free one)"
    )
