#!/usr/bin/env bash
# Set up rough_map on a fresh Debian machine with Python >= 3.11 and pip.
#   bash .ci/setup.sh          install rough_map (and open3d's system library)
#   bash .ci/setup.sh --dev    also the test tools (pytest, hypothesis, ruff)
set -euo pipefail
cd "$(dirname "$0")/.."

extras=""
[ "${1:-}" = "--dev" ] && extras="[dev]"

# open3d loads libusb-1.0 at import time; Debian ships it as libusb-1.0-0.
if ! /sbin/ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = "0" ]; then
    echo "setup: installing libusb-1.0-0 (needed by open3d)" >&2
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
  elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    echo "setup: installing libusb-1.0-0 (needed by open3d)" >&2
    sudo apt-get update -qq
    sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "setup: open3d needs the Debian package libusb-1.0-0. Run this, then again:" >&2
    echo "    sudo apt-get install -y libusb-1.0-0" >&2
    exit 1
  fi
fi

python3 -m pip install --quiet --disable-pip-version-check -e ".${extras}"
command -v pyenv >/dev/null 2>&1 && pyenv rehash || true
if ! command -v rough-map >/dev/null 2>&1; then
  echo "setup: installed, but 'rough-map' is not on PATH; use 'python3 -m rough_map' or add" >&2
  echo "       $(python3 -c 'import sysconfig; print(sysconfig.get_path("scripts"))') to PATH" >&2
fi
python3 -c "import open3d" 2>/dev/null || { echo "setup: open3d does not import" >&2; exit 1; }
echo "setup: rough_map is ready" >&2
