#!/usr/bin/env bash
# One-time set-up: system libraries for gmsh / off-screen pyvista, then a virtual environment with femreg and the
# extras the demos and tests use (all,test; `make docs` adds docs).
# Idempotent: a second run only checks.  Usage: scripts/setup.sh [VENV_DIR] [EXTRAS]
set -euo pipefail
VENV=${1:-.venv}
EXTRAS=${2:-all,test}
PKGS="libglu1-mesa libgl1 libxcursor1 libxft2 libxinerama1 libgomp1 libegl1 libgl1-mesa-dri"
missing=()
for lib in libGLU.so.1 libGL.so.1 libXcursor.so.1 libXft.so.2 libXinerama.so.1 libgomp.so.1 libEGL.so.1; do
    # grep reads the whole list: with -q it may exit first and ldconfig's SIGPIPE fails the pipe (pipefail)
    ldconfig -p 2>/dev/null | grep "$lib" >/dev/null || missing+=("$lib")
done
if [ ${#missing[@]} -gt 0 ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        echo "setup: installing system libraries (${missing[*]} missing)"
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -qq && apt-get install -y -qq --no-install-recommends $PKGS >/dev/null
    else
        echo "setup: missing system libraries: ${missing[*]}" >&2
        echo "setup: run as root:  apt-get update && apt-get install -y --no-install-recommends $PKGS" >&2
        exit 1
    fi
fi
PY=${PYTHON:-python3}
if [ ! -x "$VENV/bin/python" ]; then
    "$PY" -m venv "$VENV" || { echo "setup: '$PY -m venv' failed; run: apt-get install -y python3-venv" >&2; exit 1; }
fi
stamp="$VENV/.femreg-installed-${EXTRAS//,/-}"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    "$VENV/bin/python" -m pip install -q --upgrade pip
    "$VENV/bin/python" -m pip install -q -e ".[$EXTRAS]"
    touch "$stamp"
fi
