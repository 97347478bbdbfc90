#!/usr/bin/env bash
# Install everything rigsfm needs on a fresh Debian/Ubuntu machine: the system libraries Open3D needs
# (mesa-vulkan-drivers lets it render offscreen on the CPU),
# Debian's colmap (an independent reader used by the export tests), Chromium (the browser tests drive it
# through Playwright; no browser download), then rigsfm with its Python and test dependencies.
set -euo pipefail
cd "$(dirname "$0")/.."

packages=(libusb-1.0-0 libgl1 libgomp1 mesa-vulkan-drivers colmap chromium)
if command -v apt-get >/dev/null 2>&1; then
  missing=()
  for package in "${packages[@]}"; do
    dpkg -s "$package" >/dev/null 2>&1 || missing+=("$package")
  done
  if [ "${#missing[@]}" -gt 0 ]; then
    sudo=""
    [ "$(id -u)" -ne 0 ] && sudo="sudo"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  fi
else
  echo "setup: no apt-get; install ${packages[*]} with your package manager" >&2
fi

python3 -m pip install -q --disable-pip-version-check -e ".[test]"
