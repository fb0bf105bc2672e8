#!/usr/bin/env bash
# Installs the shared libraries open3d-cpu needs at import time (Debian/Ubuntu package names).
set -euo pipefail
libs=(libusb-1.0.so.0 libGL.so.1 libEGL.so.1 libX11.so.6 libudev.so.1)
pkgs=(libusb-1.0-0 libgl1 libegl1 libx11-6 libudev1)
missing=()
for i in "${!libs[@]}"; do
  ldconfig -p 2>/dev/null | grep -q "${libs[$i]}" || missing+=("${pkgs[$i]}")
done
[ ${#missing[@]} -eq 0 ] && exit 0
if ! command -v apt-get >/dev/null 2>&1; then
  echo "surgtrack: missing system libraries (${missing[*]}); apt-get is not available: install them with your package manager" >&2
  exit 1
fi
sudo=""
[ "$(id -u)" -eq 0 ] || sudo="sudo"
echo "surgtrack: installing system packages: ${missing[*]}"
$sudo apt-get update -qq
DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
