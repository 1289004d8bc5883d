#!/usr/bin/env bash
# One-step set-up on a fresh Debian/Ubuntu machine: system libraries open3d loads,
# a .venv, and the project installed into it (editable, with test extras).
# Idempotent: re-running it only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}

# open3d needs libGL, libEGL and libusb at import time.
need=()
for pkg in libgl1 libegl1 libusb-1.0-0 libgomp1; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || need+=("$pkg")
done
if [ ${#need[@]} -gt 0 ]; then
    if command -v apt-get >/dev/null 2>&1; then
        SUDO=""
        [ "$(id -u)" -ne 0 ] && SUDO="sudo"
        echo "setup: installing system libraries: ${need[*]}"
        $SUDO apt-get update -qq
        DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need[@]}" >/dev/null
    else
        echo "setup: warning: cannot install ${need[*]} (no apt-get); open3d may fail to import" >&2
    fi
fi

if [ ! -x "$VENV/bin/python" ]; then
    echo "setup: creating $VENV"
    "$PYTHON" -m venv "$VENV"
fi
stamp="$VENV/.turntable-installed"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    echo "setup: installing turntable and its dependencies into $VENV"
    "$VENV/bin/python" -m pip install -q --upgrade pip
    "$VENV/bin/python" -m pip install -q -e ".[test]"
    touch "$stamp"
fi
"$VENV/bin/python" -c "import open3d, cv2, trimesh, skimage, rerun" \
    || { echo "setup: dependency import check failed" >&2; exit 1; }
