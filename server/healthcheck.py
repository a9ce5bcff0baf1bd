"""`python -m server.healthcheck`: exit 0 if this container's server is ready (the Docker HEALTHCHECK).

Reads the port from PHIM_PORT (default 8080) and asks GET /health/ready on 127.0.0.1, over HTTPS when
PHIM_TLS_CERT is set (the certificate is not checked: this is the container asking itself). Standard library
only.
"""

from __future__ import annotations

import os
import ssl
import sys
import urllib.error
import urllib.request


def check(port: int, timeout_s: float = 3.0, tls: bool = False) -> tuple[bool, str]:
    url = f"{'https' if tls else 'http'}://127.0.0.1:{port}/health/ready"
    context = None
    if tls:
        context = ssl.create_default_context()
        context.check_hostname, context.verify_mode = False, ssl.CERT_NONE
    try:
        with urllib.request.urlopen(url, timeout=timeout_s, context=context) as resp:
            return resp.status == 200, f"{url}: {resp.status}"
    except urllib.error.HTTPError as e:
        return False, f"{url}: {e.code} {e.read()[:200].decode(errors='replace')}"
    except OSError as e:
        return False, f"{url}: {e}"


def main() -> int:
    ok, detail = check(int(os.environ.get("PHIM_PORT", "8080")), tls=bool(os.environ.get("PHIM_TLS_CERT")))
    print(detail)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
