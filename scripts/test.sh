#!/usr/bin/env bash
# Install into .venv (CPU torch first, from the machine's disk), lint, type-check and run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/pip install -q torch==2.13.0
.venv/bin/pip install -q -e ".[test,ray,viewer]"   # ray: tests/executors/test_ray.py; viewer: phd view
# The page's browser tests (tests/page) drive Debian's chromium through its chromedriver;
# without them (not root, no apt) those tests skip and say why.
if ! { command -v chromium && command -v chromedriver; } > /dev/null && [ "$(id -u)" = 0 ] && command -v apt-get > /dev/null; then
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver > /dev/null; } \
        || echo "scripts/test.sh: could not install chromium; the browser tests will skip" >&2
fi
# Lint (ruff: pyflakes, pycodestyle errors, import order) and a basic type check ([tool.ruff],
# [tool.mypy] in pyproject.toml), then the tests.
.venv/bin/ruff check .
.venv/bin/mypy
.venv/bin/python -m pytest -q "$@"
