#!/usr/bin/env bash
# Set up rough_map in a virtual environment, on a fresh Debian or Ubuntu machine.
#   bash .ci/setup.sh          install rough_map into .venv (and the Debian packages it needs)
#   bash .ci/setup.sh --dev    also the test tools (pytest, hypothesis, ruff, mypy, import-linter, ...)
#   bash .ci/setup.sh --latest [--dev]   the newest releases pip serves within pyproject's
#                              ranges, not the tested ones of constraints.txt (a developer's
#                              check of new releases; CI installs the tested set)
#
# The environment is, in this order: ./.venv if it is already a virtual environment; the
# virtual environment that is active (VIRTUAL_ENV), linked as ./.venv; otherwise a new ./.venv
# made with the first python3 on PATH. The system's site-packages are never touched, so this
# works on an "externally managed" (PEP 668) python3 such as Debian's and Ubuntu's.
# Afterwards `.venv/bin/rough-map` and `.venv/bin/python` work in the same shell.
set -euo pipefail
cd "$(dirname "$0")/.."

extras=""
lock=(-c constraints.txt)
for arg in "$@"; do
  case "$arg" in
    --dev) extras="[dev]" ;;
    --latest) lock=() ;;
    *) echo "setup: unknown option '$arg' (use --dev, --latest or nothing)" >&2; exit 2 ;;
  esac
done

say() { echo "setup: $*" >&2; }

# Root is available: we are root, or sudo works without a password, or sudo can ask for one.
can_root() {
  [ "$(id -u)" = "0" ] && return 0
  command -v sudo >/dev/null 2>&1 || return 1
  sudo -n true 2>/dev/null || [ -t 0 ]
}
as_root() { if [ "$(id -u)" = "0" ]; then "$@"; else sudo "$@"; fi; }

# Install all the missing Debian packages in one apt run, or print the one command to run.
apt_line() {
  say "rough_map needs the Debian package(s) $*; installing them needs root."
  say "Run this, then the set-up again:"
  echo "    sudo apt-get update && sudo apt-get install -y $*" >&2
  exit 1
}
apt_install() {
  [ "$#" -gt 0 ] || return 0
  can_root || apt_line "$@"
  say "installing the Debian package(s) $* through apt"
  # sudo may still refuse (a user at a terminal who is not a sudoer): then say what to run.
  if ! as_root apt-get update -qq \
    || ! as_root env DEBIAN_FRONTEND=noninteractive DEBCONF_NOWARNINGS=yes \
      apt-get install -y -qq "$@" >/dev/null; then
    apt_line "$@"
  fi
}

need=()
# open3d's wheel loads libusb-1.0, libGL and libEGL at import time (Debian: libusb-1.0-0,
# libgl1, libegl1); a desktop has them, a server or container usually does not.
# (ldconfig's output is read whole: `ldconfig -p | grep -q` can fail under pipefail when
# grep exits first and ldconfig dies of SIGPIPE.)
libs=$(/sbin/ldconfig -p 2>/dev/null || true)
for lib in libusb-1.0.so.0:libusb-1.0-0 libGL.so.1:libgl1 libEGL.so.1:libegl1; do
  case "$libs" in *[[:space:]]"${lib%%:*}"[[:space:]]*) ;; *) need+=("${lib#*:}") ;; esac
done

venv=.venv
make_venv=""
if [ -x .venv/bin/python ] && [ ! -L .venv ]; then
  say "using the project's virtual environment .venv"
elif [ -n "${VIRTUAL_ENV:-}" ] && [ -x "${VIRTUAL_ENV}/bin/python" ]; then
  say "using the active virtual environment ${VIRTUAL_ENV} (linked as .venv)"
  ln -sfn "${VIRTUAL_ENV}" .venv
else
  [ -L .venv ] && rm -f .venv
  make_venv=1
  py=$(command -v python3 || true)
  if [ -z "$py" ]; then
    need+=(python3 python3-venv)
  else
    if ! "$py" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
      say "rough_map needs Python >= 3.11; $py is $("$py" -c 'import sys; print(sys.version.split()[0])')"
      exit 1
    fi
    # Debian and Ubuntu split venv (and its ensurepip) into python3-venv / python3.X-venv.
    if ! "$py" -c 'import ensurepip, venv' >/dev/null 2>&1; then
      need+=("python$("$py" -c 'import sys; print("%d.%d" % sys.version_info[:2])')-venv")
    fi
  fi
fi

apt_install ${need[@]+"${need[@]}"}

if [ -n "$make_venv" ]; then
  py=$(command -v python3)
  say "making the virtual environment .venv with $py"
  "$py" -m venv .venv
fi

if [ "${#lock[@]}" -gt 0 ]; then
  versions="the tested versions of constraints.txt"
else
  versions="the newest versions pip serves (--latest)"
fi
say "installing rough_map${extras} and its dependencies into .venv, $versions" \
  "(about 1 GB on the first run: a few minutes; pip shows each package)"
.venv/bin/python -m pip install --disable-pip-version-check --progress-bar off \
  ${lock[@]+"${lock[@]}"} -e ".${extras}" 2>&1 | { grep --line-buffered -v '^Requirement already satisfied' || true; } >&2
if ! err=$(.venv/bin/python -c "import open3d" 2>&1); then
  say "open3d does not import: $(printf '%s\n' "$err" | tail -n 1)"
  exit 1
fi
say "rough_map is ready: .venv/bin/rough-map (or 'source .venv/bin/activate', then rough-map)"
