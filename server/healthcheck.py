"""`python -m server.healthcheck`: exit 0 if this container's server is ready (the Docker HEALTHCHECK).

Reads the port from PHIM_PORT (default 8080) and asks GET /health/ready on 127.0.0.1. Standard library only.
"""

from __future__ import annotations

import os
import sys
import urllib.error
import urllib.request


def check(port: int, timeout_s: float = 3.0) -> tuple[bool, str]:
    url = f"http://127.0.0.1:{port}/health/ready"
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as resp:
            return resp.status == 200, f"{url}: {resp.status}"
    except urllib.error.HTTPError as e:
        return False, f"{url}: {e.code} {e.read()[:200].decode(errors='replace')}"
    except OSError as e:
        return False, f"{url}: {e}"


def main() -> int:
    ok, detail = check(int(os.environ.get("PHIM_PORT", "8080")))
    print(detail)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
