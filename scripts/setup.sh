#!/usr/bin/env bash
# Set up rigsfm on a fresh Debian 12 / Ubuntu 24.04 machine, for the distribution's own Python:
#  1. system packages through apt (as root, or with sudo): Python's venv and pip, the libraries Open3D
#     needs (libusb, GL, OpenMP; mesa-vulkan-drivers lets it render offscreen on the CPU), Debian's colmap
#     (an independent reader the export tests use) and a Chromium for the browser tests;
#  2. a project virtual environment in .venv (the system Python is never touched: PEP 668);
#  3. rigsfm with its test extras, editable, into .venv.
# Afterwards: .venv/bin/rigsfm ..., .venv/bin/python -m pytest. Re-running it is quick and changes nothing.
# `--apt-only` stops after step 1. Another apt or dpkg (unattended-upgrades right after boot) is waited for,
# up to RIGSFM_APT_WAIT seconds (default 600); RIGSFM_APT_LOCKS replaces the lock files waited for (tests).
set -euo pipefail
cd "$(dirname "$0")/.."

say() { printf 'setup: %s\n' "$*" >&2; }

apt_only=false
for argument in "$@"; do
  case "$argument" in
    --apt-only) apt_only=true ;;
    *) say "unknown option $argument (the only one is --apt-only)"; exit 2 ;;
  esac
done

# Runs a command with its stderr kept back, then shows that stderr less the lines matching the noise pattern
# $1, which are harmless and only alarm (the exit status is the command's).
quietly() {
  local noise=$1 status=0 log
  shift
  log=$(mktemp)
  "$@" 2>"$log" || status=$?
  grep -Ev "$noise" "$log" >&2 || true
  rm -f "$log"
  return "$status"
}

apt_wait=${RIGSFM_APT_WAIT:-600}
# shellcheck disable=SC2206
apt_locks=(${RIGSFM_APT_LOCKS:-/var/lib/dpkg/lock-frontend /var/lib/dpkg/lock /var/lib/apt/lists/lock /var/cache/apt/archives/lock})

# The process holding a lock on file $1, from /proc/locks (apt and dpkg take POSIX locks, which flock(1) and
# bash cannot test); empty when the file is free or missing.
lock_holder() {
  local inode pid fd
  inode=$(stat -L -c %i "$1" 2>/dev/null) || return 0
  for pid in $(awk -v inode="$inode" '$2 == "->" { next } { n = split($0, f, " "); for (i = 1; i <= n; i++)
                 if (f[i] ~ /^[0-9a-f]+:[0-9a-f]+:[0-9]+$/) { split(f[i], d, ":"); if (d[3] == inode) print f[i-1] } }' \
                 /proc/locks 2>/dev/null); do
    # Another file system may hold the same inode number: the holder must have this very file open.
    if [ ! -r "/proc/$pid/fd" ]; then echo "$pid"; return 0; fi
    for fd in /proc/"$pid"/fd/*; do
      if [ "$(readlink -f "$fd" 2>/dev/null)" = "$(readlink -f "$1")" ]; then echo "$pid"; return 0; fi
    done
  done
}

# Waits until no apt or dpkg lock is held, saying once what it waits for; gives up after $apt_wait seconds.
wait_for_apt() {
  local start=$SECONDS lock pid said=false
  while :; do
    pid=
    for lock in "${apt_locks[@]}"; do
      pid=$(lock_holder "$lock")
      [ -n "$pid" ] && break
    done
    [ -z "$pid" ] && return 0
    local who="process $pid ($(cat "/proc/$pid/comm" 2>/dev/null || echo gone))"
    if [ $((SECONDS - start)) -ge "$apt_wait" ]; then
      say "gave up after ${apt_wait} s: $lock is still held by $who; let it finish (or stop it) and run setup again"
      exit 1
    fi
    if ! $said; then
      say "waiting up to ${apt_wait} s for $who, which holds $lock (another apt or dpkg: unattended-upgrades runs after boot)"
      said=true
    fi
    sleep 1
  done
}

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
    # apt-get waits for dpkg's lock itself (the timeout covers the race with the check), not for the lists lock
    # of `update`: wait_for_apt does both. debconf's note that apt-utils is missing is harmless.
    wait_for_apt
    as_root apt-get -o DPkg::Lock::Timeout="$apt_wait" update -qq
    wait_for_apt
    quietly '^debconf: delaying package configuration' as_root env DEBIAN_FRONTEND=noninteractive \
      apt-get -o DPkg::Lock::Timeout="$apt_wait" install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  fi
else
  say "no apt-get: install ${packages[*]} (or your distribution's equivalents) yourself"
fi
if $apt_only; then say "system packages ready"; exit 0; fi

# A fresh install takes about 3 GiB (Open3D, OpenCV, pycolmap and their wheels while pip unpacks them): say so
# before pip fails half-way with "No space left on device". RIGSFM_SETUP_NEED_MB replaces the need (tests).
need_mb=${RIGSFM_SETUP_NEED_MB:-4096}
if [ ! -x .venv/bin/rigsfm ]; then
  for folder in . "${TMPDIR:-/tmp}"; do
    free_mb=$(df -Pm "$folder" 2>/dev/null | awk 'NR == 2 { print $4 }')
    if [ -n "$free_mb" ] && [ "$free_mb" -lt "$need_mb" ]; then
      say "only ${free_mb} MiB free on $(cd "$folder" && pwd) (the file system of $( [ "$folder" = . ] && echo the project || echo TMPDIR)); the install needs about ${need_mb} MiB: free some space and run setup again"
      exit 1
    fi
  done
fi

python=/usr/bin/python3
[ -x "$python" ] || python=$(command -v python3)
if [ ! -x .venv/bin/python ]; then
  say "creating the virtual environment .venv with $($python --version)"
  "$python" -m venv .venv
fi
# Harmless pip noise: setuptools' banner on every editable install, and pip's note on each configured package
# location (e.g. a --find-links folder) that does not exist; pip's errors and other warnings still show.
pip_noise='BuildBackendWarning: Editable installation|^ *!!$|^ *\*+$|Please be careful with folders in your|'
pip_noise+='name as your package as they may take precedence|with strategy, WheelFile|^ *$|^WARNING: Location .* is ignored'
pip() { quietly "$pip_noise" .venv/bin/python -m pip "$@"; }
pip install -q --disable-pip-version-check --upgrade pip >/dev/null
pip install -q --disable-pip-version-check -e ".[test]"
# aniposelib (the export test reads the toml export with it) pins the GUI build of OpenCV, which would
# shadow the headless one: install it without its dependencies (those it imports are in the test extra;
# not jax, which only its triangulation needs: README, "Inspect and export").
pip install -q --disable-pip-version-check --no-deps "aniposelib==0.8.0"
if [ "$browser" = playwright ]; then
  say "installing Playwright's Chromium for the browser tests"
  as_root .venv/bin/python -m playwright install-deps chromium >/dev/null
  .venv/bin/python -m playwright install chromium >/dev/null
fi
say "ready: .venv/bin/rigsfm --help"
