#!/usr/bin/env bash
# Installs the engine, torch 2.13.0 (CPU) and the test tools into .venv and runs the test suite.
# Extra arguments go to pytest (e.g. `-m slow` for the long tests, `-k geometry`).
set -euo pipefail
INTERLEAVE_EXTRA=test
. "$(dirname "${BASH_SOURCE[0]}")/_env.sh"
python -m pytest -q -p no:cacheprovider --timeout 900 "$@"
