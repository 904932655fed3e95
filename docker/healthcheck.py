#!/usr/bin/env python3
"""The images' HEALTHCHECK: exit 0 when ``/readyz`` of the server in this container answers 200,
else 1 with the reason on stdout (Docker keeps it in ``docker inspect``). Standard library only.

It asks the port the server listens on, ``$COLLIDER_PORT`` (default 8000), on loopback unless
``$COLLIDER_HOST`` names one specific address; ``/readyz`` needs no token.
"""

from __future__ import annotations

import os
import sys
import urllib.error
import urllib.request

WILDCARD_HOSTS = ("", "0.0.0.0", "::")


def readyz_url(environ=os.environ) -> str:
    host = environ.get("COLLIDER_HOST", "")
    host = "127.0.0.1" if host in WILDCARD_HOSTS else host
    if ":" in host:  # an IPv6 address goes in brackets in a URL
        host = f"[{host}]"
    return f"http://{host}:{environ.get('COLLIDER_PORT', '8000')}/readyz"


def main() -> int:
    url = readyz_url()
    try:
        with urllib.request.urlopen(url, timeout=2) as response:
            return 0 if response.status == 200 else 1
    except urllib.error.HTTPError as exc:  # 503 while loading or draining
        print(f"{url}: {exc.code} {exc.reason}")
    except (urllib.error.URLError, OSError) as exc:
        print(f"{url}: {getattr(exc, 'reason', exc)}")
    return 1


if __name__ == "__main__":
    sys.exit(main())
