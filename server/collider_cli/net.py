"""Network addresses: shared by ``collider serve`` and the browser views, which both warn when
they listen beyond this machine."""

from __future__ import annotations

import ipaddress


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or an IP address) is this machine only: ``localhost``, 127.0.0.0/8
    or ::1. Other names and addresses (0.0.0.0 included) are not."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
