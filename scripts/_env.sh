# Sourced by scripts/demo.sh and scripts/test.sh: makes .venv with what they need.
# Set INTERLEAVE_EXTRA before sourcing: empty for the engine alone (no torch), "test" for tests + torch.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
extra="${INTERLEAVE_EXTRA:-}"
py="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
    "$py" -m venv .venv
fi
# torch is pinned to the CPU build (2.13.0): an unpinned torch pulls gigabytes of CUDA packages.
stamp=".venv/.installed-${extra:-engine}"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    .venv/bin/python -m pip install -q --upgrade pip
    if [ -n "$extra" ]; then
        .venv/bin/python -m pip install -q -e ".[$extra]"
    else
        .venv/bin/python -m pip install -q -e .
    fi
    touch "$stamp"
fi
# Headless OpenGL: EGL with Mesa's llvmpipe when there is no GPU (Debian: libegl1 libgl1 + Mesa drivers).
if ! .venv/bin/python -c "import moderngl; moderngl.create_standalone_context(backend='egl').release()" 2>/dev/null; then
    if command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
        echo "installing Debian packages for headless OpenGL (libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri)" >&2
        apt-get update -qq && apt-get install -y -qq libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri >/dev/null
    else
        echo "headless OpenGL (EGL) is missing: install Debian's libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri" >&2
        exit 1
    fi
fi
# The tests of `interleave play` open its window under Xvfb (a virtual X server; GLX through Mesa).
if [ "$extra" = test ] && ! command -v Xvfb >/dev/null; then
    if command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
        echo "installing Debian packages for the window tests (xvfb libglx-mesa0 libgl1-mesa-dri)" >&2
        apt-get update -qq && apt-get install -y -qq xvfb libglx-mesa0 libgl1-mesa-dri >/dev/null \
            || echo "could not install xvfb: the window tests of 'interleave play' are skipped" >&2
    else
        echo "no Xvfb: the window tests of 'interleave play' are skipped (Debian: apt-get install xvfb)" >&2
    fi
fi
export PATH="$root/.venv/bin:$PATH"
