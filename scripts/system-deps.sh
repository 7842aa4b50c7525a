#!/usr/bin/env bash
# Debian packages the Python wheels need at run time (Open3D: libusb, OpenMP, GL). Installs only
# what is missing, so a second run is instant. Needs root (or sudo) on a machine that lacks them.
set -euo pipefail
need=()
have_lib() { ldconfig -p 2>/dev/null | grep -q "$1"; }
have_lib libusb-1.0.so.0 || need+=(libusb-1.0-0)
have_lib libgomp.so.1 || need+=(libgomp1)
have_lib libGL.so.1 || need+=(libgl1)
have_lib libEGL.so.1 || need+=(libegl1)
[ ${#need[@]} -eq 0 ] && exit 0
echo "installing Debian packages: ${need[*]}"
SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${need[@]}"
