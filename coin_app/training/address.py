"""A Ray cluster address, checked before ``ray.init``: its form, and a TCP probe bounded by a time-out."""

from __future__ import annotations

import socket
from urllib.parse import urlparse

from coin_app.evaluation.limits import CONNECT_TIMEOUT_S, check_timeout


def check_address(address: str | None, timeout: float = CONNECT_TIMEOUT_S) -> None:
    """A ValueError unless ``address`` is None, ``auto``/``local``, or a ``[ray://]host:port`` that answers within ``timeout`` s."""
    timeout = check_timeout(timeout, "--connect-timeout")
    if address in (None, "auto", "local"):
        return
    parsed = urlparse(address if "://" in address else f"tcp://{address}")
    try:
        port = parsed.port
    except ValueError:
        port = None
    if parsed.scheme not in ("tcp", "ray") or not parsed.hostname or port is None:
        raise ValueError(f"bad --address {address!r}; allowed: auto, local, HOST:PORT (GCS address) or ray://HOST:PORT (Ray client)")
    try:
        with socket.create_connection((parsed.hostname, port), timeout=timeout):
            pass
    except OSError as exc:
        reason = "no answer" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        raise ValueError(
            f"cannot reach a Ray cluster at {address} within --connect-timeout {timeout:g} s: {reason}; "
            "allowed: the address of a running head (`ray start --head` there), or no --address for a local session"
        ) from exc
