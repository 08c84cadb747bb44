#!/usr/bin/env bash
# Install into .venv (CPU torch first, from the machine's disk) and run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/pip install -q torch==2.13.0
.venv/bin/pip install -q -e ".[test,ray,viewer]"   # ray: tests/executors/test_ray.py (about 30 s of the suite)
# The page's browser tests (tests/page) drive Debian's chromium through its chromedriver;
# without them (not root, no apt) those tests skip and say why.
if ! { command -v chromium && command -v chromedriver; } > /dev/null && [ "$(id -u)" = 0 ] && command -v apt-get > /dev/null; then
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver > /dev/null; } \
        || echo "scripts/test.sh: could not install chromium; the browser tests will skip" >&2
fi
.venv/bin/python -m pytest -q "$@"
