#!/usr/bin/env bash
# Install into .venv (CPU torch first, from the machine's disk) and run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/pip install -q torch==2.13.0
.venv/bin/pip install -q -e ".[test,ray]"   # ray: tests/executors/test_ray.py (about 30 s of the suite)
.venv/bin/python -m pytest -q "$@"
