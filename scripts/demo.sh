#!/usr/bin/env bash
# Install into .venv (CPU torch first, from the machine's disk) and run the demo.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/pip install -q torch==2.13.0
.venv/bin/pip install -q -e .
.venv/bin/phd demo "$@"
echo "(phd and python above are .venv/bin/phd and .venv/bin/python: source .venv/bin/activate first)"
