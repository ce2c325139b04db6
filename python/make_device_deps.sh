#!/usr/bin/env bash
# Packs the header-only dependencies a GPU machine may lack (xsimd, nlohmann-json with its CMake
# config, stb) from this machine into one .tar.xz for python/device_test.sh (EPONA_DEVICE_DEPS).
# The archive holds one folder, epona-device-deps/, laid out as a prefix:
#   include/xsimd  include/nlohmann  include/stb  share/cmake/nlohmann_json
# (nlohmann's targets file finds its headers three folders above itself, so the prefix works
# wherever it is unpacked).
# Usage: python/make_device_deps.sh OUT.tar.xz
set -euo pipefail
die() { echo "make_device_deps: $*" >&2; exit 1; }
[[ $# -eq 1 && $1 == *.tar.xz ]] || die "usage: $0 OUT.tar.xz"
out=$(realpath -m "$1")

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
prefix=$work/epona-device-deps
mkdir -p "$prefix/include" "$prefix/share/cmake"

for dir in xsimd nlohmann stb; do
  [[ -d /usr/include/$dir ]] || die "/usr/include/$dir is missing (apt install libxsimd-dev nlohmann-json3-dev libstb-dev)"
  cp -rL "/usr/include/$dir" "$prefix/include/"
  echo "make_device_deps: include/$dir from /usr/include/$dir"
done

# The config folder sits three levels below its prefix in each of these layouts.
config=""
for dir in /usr/share/cmake/nlohmann_json /usr/lib/cmake/nlohmann_json /usr/local/share/cmake/nlohmann_json \
           /usr/local/lib/cmake/nlohmann_json; do
  [[ -f $dir/nlohmann_jsonConfig.cmake ]] && { config=$dir; break; }
done
[[ -n $config ]] || die "no nlohmann_jsonConfig.cmake under /usr/share/cmake or /usr/lib/cmake"
cp -rL "$config" "$prefix/share/cmake/nlohmann_json"
echo "make_device_deps: share/cmake/nlohmann_json from $config"

mkdir -p "$(dirname "$out")"
tar -C "$work" -cJf "$out" epona-device-deps
echo "make_device_deps: wrote $out ($(du -h "$out" | cut -f1))"
