#!/usr/bin/env bash
# Set up rigsfm on a fresh Debian 12 / Ubuntu 24.04 machine, for the distribution's own Python:
#  1. system packages through apt (as root, or with sudo): Python's venv and pip, the libraries Open3D
#     needs (libusb, GL, OpenMP; mesa-vulkan-drivers lets it render offscreen on the CPU), Debian's colmap
#     (an independent reader the export tests use) and a Chromium for the browser tests;
#  2. a project virtual environment in .venv (the system Python is never touched: PEP 668);
#  3. rigsfm with its test extras, editable, into .venv.
# Afterwards: .venv/bin/rigsfm ..., .venv/bin/python -m pytest. Re-running it is quick and changes nothing.
set -euo pipefail
cd "$(dirname "$0")/.."

say() { printf 'setup: %s\n' "$*" >&2; }

as_root() {
  if [ "$(id -u)" -eq 0 ]; then "$@"
  elif command -v sudo >/dev/null 2>&1; then sudo "$@"
  else say "need root for: $*  (run as root, or install sudo)"; exit 1; fi
}

. /etc/os-release 2>/dev/null || true
packages=(python3 python3-venv python3-pip libusb-1.0-0 libgl1 libgomp1 mesa-vulkan-drivers colmap)
# Debian ships Chromium as a package; Ubuntu only as a snap (its deb is a snap wrapper), so there the
# tests use Playwright's own Chromium build instead (downloaded below, with its system libraries).
browser=playwright
if [ "${ID:-}" = debian ]; then packages+=(chromium); browser=debian; fi

if command -v apt-get >/dev/null 2>&1; then
  missing=()
  for package in "${packages[@]}"; do
    dpkg-query -W -f='${Status}' "$package" 2>/dev/null | grep -q "install ok installed" || missing+=("$package")
  done
  if [ "${#missing[@]}" -gt 0 ]; then
    say "installing ${missing[*]}"
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  fi
else
  say "no apt-get: install ${packages[*]} (or your distribution's equivalents) yourself"
fi

python=/usr/bin/python3
[ -x "$python" ] || python=$(command -v python3)
if [ ! -x .venv/bin/python ]; then
  say "creating the virtual environment .venv with $($python --version)"
  "$python" -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip >/dev/null
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test]"
# aniposelib (the export test reads the toml export with it) pins the GUI build of OpenCV, which would
# shadow the headless one: install it without its dependencies (those it imports are in the test extra).
.venv/bin/python -m pip install -q --disable-pip-version-check --no-deps "aniposelib==0.8.0"
if [ "$browser" = playwright ]; then
  say "installing Playwright's Chromium for the browser tests"
  as_root .venv/bin/python -m playwright install-deps chromium >/dev/null
  .venv/bin/python -m playwright install chromium >/dev/null
fi
say "ready: .venv/bin/rigsfm --help"
