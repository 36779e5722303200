#!/usr/bin/env bash
# Set up diffuser-lab in ./.venv on a Debian/Ubuntu machine and run a job.
#   bash scripts/dev.sh demo [hydra overrides...]   set up what the demo needs, then run it (diffuser-lab)
#   bash scripts/dev.sh test [pytest args...]       set up everything (the test extra), then run the test suite
#   bash scripts/dev.sh setup                       set up only
# System packages (open3d's shared libraries, python venv; test and setup: qemu-user) come from apt-get when missing:
# as root directly, otherwise through sudo; without either, the script says what to install.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
APT_PACKAGES="python3 python3-venv python3-pip libusb-1.0-0 libgl1 libegl1 libx11-6 libudev1 libgomp1"
# test and setup only: qemu-x86_64 for tests/test_isa.py's emulated AMD CPU (-cpu EPYC-Rome). Optional
# outside CI (without root or sudo the test skips, saying so); under CI=true its absence fails the test.
TEST_APT_PACKAGES="qemu-user"

system_deps() {  # $1: the packages; $2: "optional" when the job can go on without them
  command -v dpkg >/dev/null 2>&1 || return 0  # not Debian-like: the user's own business
  local missing=()
  for p in $1; do
    case $p in python3*) command -v python3 >/dev/null && python3 -c "import venv, ensurepip" 2>/dev/null && continue;; esac
    dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
  done
  [ ${#missing[@]} -eq 0 ] && return 0
  local sudo=""
  if [ "$(id -u)" -ne 0 ]; then
    if command -v sudo >/dev/null 2>&1; then sudo="sudo"; else
      if [ "${2:-}" = optional ] && [ "${CI:-}" != true ]; then
        echo "note: without ${missing[*]} (apt-get install -y ${missing[*]} as root) the tests skip what needs it" >&2
        return 0
      fi
      echo "diffuser-lab needs these system packages: ${missing[*]}" >&2
      echo "install them as root: apt-get install -y ${missing[*]}" >&2
      exit 1
    fi
  fi
  echo "installing system packages: ${missing[*]}"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
}

# The demo's first run: uv (from PyPI, into the venv) installs the package in a fraction of pip's
# time (parallel downloads, no bytecode compiled up front); pip does it where uv is unavailable.
fast_install() {
  "$VENV/bin/python" -m pip install -q --disable-pip-version-check uv >/dev/null 2>&1 || return 1
  "$VENV/bin/uv" pip install -q --python "$VENV/bin/python" -e . && return 0
  echo "uv could not install the package: installing it with pip" >&2
  return 1
}

python_env() {  # $1: the extra to install ("" for the demo: the package alone; "test": everything)
  local extra=${1:-} stamp="$VENV/.installed${1:+-$1}" full="$VENV/.installed-test"
  # an environment set up for the tests has what the demo needs
  if [ -z "$extra" ] && [ -f "$full" ] && [ ! pyproject.toml -nt "$full" ]; then return 0; fi
  if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    [ -x "$VENV/bin/python" ] || python3 -m venv "$VENV"
    if [ -z "$extra" ] && fast_install; then touch "$stamp"; return 0; fi
    "$VENV/bin/python" -m pip install -q --upgrade pip
    "$VENV/bin/python" -m pip install -q --disable-pip-version-check -e ".${extra:+[$extra]}"
    touch "$stamp"
  fi
}

cmd=${1:-demo}
[ $# -gt 0 ] && shift
system_deps "$APT_PACKAGES"
case $cmd in demo) python_env "" ;; *) system_deps "$TEST_APT_PACKAGES" optional; python_env test ;; esac
case $cmd in
  setup) ;;
  demo) exec "$VENV/bin/diffuser-lab" "$@" ;;
  test) exec "$VENV/bin/python" -m pytest "$@" ;;
  *) echo "usage: bash scripts/dev.sh {demo|test|setup} [args...]" >&2; exit 2 ;;
esac
