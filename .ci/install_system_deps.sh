#!/usr/bin/env bash
# Install the Debian system packages neuromotor needs on a machine with no display and no GPU:
# the libraries of off-screen rendering (pyvista/VTK through EGL + Mesa), headless Chromium (the
# HTML viewer's browser test), Node.js with npm (three.js and the Khronos glTF validator,
# installed by .ci/install from package.json) and Blender with Debian's NumPy (its glTF
# importer needs NumPy; tests/io/test_blender.py imports our exports in it). Idempotent: packages already present are left
# alone and apt is not touched at all when nothing is missing. Runs as root, or through sudo.
#
#   .ci/install_system_deps.sh            # install what is missing
#   .ci/install_system_deps.sh --check    # only report; exit 1 if something is missing
set -euo pipefail

PACKAGES=(libegl1 libegl-mesa0 libgl1-mesa-dri chromium blender python3-numpy)
# Node.js from any source will do (a machine may carry a newer one than Debian's).
if ! command -v npm >/dev/null 2>&1; then
    PACKAGES+=(nodejs npm)
fi

missing=()
for pkg in "${PACKAGES[@]}"; do
    # dpkg -s succeeds for removed-but-configured packages too; require "install ok installed".
    status=$(dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null || true)
    if [[ "$status" != "install ok installed" ]]; then
        missing+=("$pkg")
    fi
done

if [[ ${#missing[@]} -eq 0 ]]; then
    echo "system deps: all present (${PACKAGES[*]})"
    exit 0
fi

if [[ "${1:-}" == "--check" ]]; then
    echo "system deps: missing ${missing[*]}" >&2
    exit 1
fi

if ! command -v apt-get >/dev/null 2>&1; then
    echo "system deps: missing ${missing[*]} and apt-get is not available; install the" \
         "equivalents of these Debian packages with your package manager" >&2
    exit 1
fi

if [[ $(id -u) -eq 0 ]]; then
    SUDO=()
elif command -v sudo >/dev/null 2>&1; then
    SUDO=(sudo -n)    # never prompt: fail clearly instead of hanging in CI
else
    echo "system deps: missing ${missing[*]}; run this script as root or install sudo" >&2
    exit 1
fi

echo "system deps: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
"${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive apt-get update -qq
"${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
    "${missing[@]}" >/dev/null
echo "system deps: done"
