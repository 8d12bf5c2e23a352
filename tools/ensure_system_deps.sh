#!/usr/bin/env bash
# Check the system tools the build needs and install the missing ones with apt-get.
#   python3.11 (+ venv, headers), cmake, g++, make   (rclpy and the ros-* wheels are cp311;
#   colcon builds rotor_id_msgs with CMake and a C++ compiler)
# Does nothing (and needs no network) when everything is present.
set -euo pipefail

PYTHON="${1:-python3.11}"
missing=()
command -v cmake >/dev/null 2>&1 || missing+=(cmake)
command -v g++ >/dev/null 2>&1 || missing+=(g++)
command -v make >/dev/null 2>&1 || missing+=(make)
if ! command -v "$PYTHON" >/dev/null 2>&1; then
  missing+=(python3.11 python3.11-venv python3.11-dev)
else
  "$PYTHON" -c 'import ensurepip, venv' >/dev/null 2>&1 || missing+=(python3.11-venv)
  "$PYTHON" -c 'import os, sys, sysconfig
sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' \
    || missing+=(python3.11-dev)
fi

[ ${#missing[@]} -eq 0 ] && exit 0

echo "ensure_system_deps: missing ${missing[*]}; installing with apt-get" >&2
if [ "$(id -u)" -eq 0 ]; then
  sudo=()
elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
  sudo=(sudo -n)
else
  echo "ensure_system_deps: not root and no password-less sudo: run" \
       "'apt-get install ${missing[*]}' as root, then re-run make" >&2
  exit 1
fi
if ! command -v apt-get >/dev/null 2>&1; then
  echo "ensure_system_deps: no apt-get here: install ${missing[*]} with your package manager" >&2
  exit 1
fi
export DEBIAN_FRONTEND=noninteractive
"${sudo[@]}" apt-get update
"${sudo[@]}" apt-get install -y --no-install-recommends "${missing[@]}"
