#!/usr/bin/env bash
# Installs everything epona needs from Debian 12 packages. Safe to run again: it only calls
# apt-get when a package is missing. The CUDA toolkit is used when present, never installed.
set -euo pipefail
packages=(g++ cmake ninja-build pkg-config libeigen3-dev libxsimd-dev doctest-dev libstb-dev
          nlohmann-json3-dev libbenchmark-dev clang libclang-rt-14-dev
          libavcodec-dev libavformat-dev libavutil-dev libswscale-dev libopenmpi-dev openmpi-bin
          python3-dev pybind11-dev python3-numpy python3-pytest)
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "setup: installing ${missing[*]}"
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi
echo "setup: all dependencies present"
