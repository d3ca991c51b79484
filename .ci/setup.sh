#!/usr/bin/env bash
# Set up rough_map in a virtual environment, on a fresh Debian or Ubuntu machine.
#   bash .ci/setup.sh          install rough_map into .venv (and the Debian packages it needs)
#   bash .ci/setup.sh --dev    also the test tools (pytest, hypothesis, ruff, mypy, ...)
#
# The environment is, in this order: ./.venv if it is already a virtual environment; the
# virtual environment that is active (VIRTUAL_ENV), linked as ./.venv; otherwise a new ./.venv
# made with the first python3 on PATH. The system's site-packages are never touched, so this
# works on an "externally managed" (PEP 668) python3 such as Debian's and Ubuntu's.
# Afterwards `.venv/bin/rough-map` and `.venv/bin/python` work in the same shell.
set -euo pipefail
cd "$(dirname "$0")/.."

extras=""
case "${1:-}" in
  "") ;;
  --dev) extras="[dev]" ;;
  *) echo "setup: unknown option '$1' (use --dev or nothing)" >&2; exit 2 ;;
esac

say() { echo "setup: $*" >&2; }

# Run a command as root: directly, through sudo, or say what to run and stop.
as_root() {
  if [ "$(id -u)" = "0" ]; then
    "$@"
  elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    sudo "$@"
  elif command -v sudo >/dev/null 2>&1 && [ -t 0 ]; then
    sudo "$@"
  else
    say "this needs root. Run this, then the set-up again:"
    echo "    sudo $*" >&2
    exit 1
  fi
}

apt_updated=""
apt_install() {
  say "installing the Debian package(s) $* through apt"
  if [ -z "$apt_updated" ]; then
    as_root apt-get update -qq
    apt_updated=1
  fi
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
}

# open3d loads libusb-1.0 at import time; Debian ships it as libusb-1.0-0.
if ! /sbin/ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  apt_install libusb-1.0-0
fi

venv=.venv
if [ -x .venv/bin/python ] && [ ! -L .venv ]; then
  say "using the project's virtual environment .venv"
elif [ -n "${VIRTUAL_ENV:-}" ] && [ -x "${VIRTUAL_ENV}/bin/python" ]; then
  say "using the active virtual environment ${VIRTUAL_ENV} (linked as .venv)"
  ln -sfn "${VIRTUAL_ENV}" .venv
else
  [ -L .venv ] && rm -f .venv
  py=$(command -v python3 || true)
  if [ -z "$py" ]; then
    apt_install python3 python3-venv
    py=$(command -v python3)
  fi
  if ! "$py" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
    say "rough_map needs Python >= 3.11; $py is $("$py" -c 'import sys; print(sys.version.split()[0])')"
    exit 1
  fi
  # Debian and Ubuntu split venv (and its ensurepip) into python3-venv / python3.X-venv.
  if ! "$py" -c 'import ensurepip, venv' >/dev/null 2>&1; then
    ver=$("$py" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
    apt_install "python${ver}-venv"
  fi
  say "making the virtual environment .venv with $py"
  "$py" -m venv .venv
fi

say "installing rough_map${extras} and its dependencies into .venv" \
  "(about 1 GB on the first run: a few minutes; pip shows each package)"
.venv/bin/python -m pip install --disable-pip-version-check --progress-bar off \
  -e ".${extras}" 2>&1 | { grep --line-buffered -v '^Requirement already satisfied' || true; } >&2
.venv/bin/python -c "import open3d" 2>/dev/null || { say "open3d does not import"; exit 1; }
say "rough_map is ready: .venv/bin/rough-map (or 'source .venv/bin/activate', then rough-map)"
