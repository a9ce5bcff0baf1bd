#!/usr/bin/env bash
# Services the tests run for real, installed where missing: Debian's nginx, for tests/test_nginx.py (the
# consistent-hash proxy of deploy/nginx/phim.conf). Called by scripts/test.sh before pytest.
# It never fails the test run: without nginx those tests skip (and fail where PHIM_REQUIRE_NGINX=1, as in CI).
set -uo pipefail

LOG=${TMPDIR:-/tmp}/phim-test-services.log

skip() {
    echo "test_services: $1; the nginx tests will be skipped"
    exit 0
}

# Debian puts nginx in /usr/sbin, which is not on a normal user's PATH (the tests look there too)
nginx_path() { command -v nginx || echo /usr/sbin/nginx; }
have_nginx() { [ -x "$(nginx_path)" ]; }

have_nginx && exit 0
command -v apt-get >/dev/null || skip "nginx is not installed and there is no apt-get"
if [ "$(id -u)" = 0 ]; then
    SUDO=()
elif command -v sudo >/dev/null && sudo -n true 2>/dev/null; then
    SUDO=(sudo -n)
else
    skip "nginx is not installed and installing it needs root (or passwordless sudo)"
fi

apt_install() {
    timeout 600 "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive \
        apt-get install -y -q --no-install-recommends nginx >>"$LOG" 2>&1
}

echo "test_services: installing nginx (apt-get, log: $LOG)"
: >"$LOG"
# the package lists may be missing (a fresh container) or stale: update only then, and try once more
if ! apt_install; then
    timeout 600 "${SUDO[@]}" apt-get update -q >>"$LOG" 2>&1
    apt_install
fi

# Where no policy-rc.d holds it back, the package's postinst starts a system nginx on port 80. The tests run
# their own nginx on free ports and do not need it: stop it rather than leave a daemon behind.
if [ -s /run/nginx.pid ]; then
    "${SUDO[@]}" "$(nginx_path)" -s stop >>"$LOG" 2>&1 || true
fi

# judged by the binary, not apt's exit status: a postinst that could not start nginx (port 80 taken) fails
# the install but leaves a working binary
have_nginx || skip "apt-get could not install nginx (see $LOG)"
echo "test_services: $("$(nginx_path)" -v 2>&1)"
