#!/usr/bin/env bash
# Installs the engine (no torch needed) into .venv and runs the frame-upsampling demo on the built-in scene.
# Extra arguments go to `interleave demo` (see `interleave demo --help`).
set -euo pipefail
INTERLEAVE_EXTRA=
. "$(dirname "${BASH_SOURCE[0]}")/_env.sh"
interleave demo "$@"
