#!/usr/bin/env bash
# Builds the `epona` Python module with CUDA on a GPU machine and runs its pytest suite there
# (tests/python: the CUDA tests run instead of skipping; CUDA float32 against the CPU within
# 1e-4, bf16 close, a session on the GPU). Run from the repository root:
#   EPONA_DEVICE_DEPS=deps.tar.xz python/device_test.sh
# EPONA_DEVICE_DEPS: the headers the machine may lack (xsimd, nlohmann-json, stb), as
#   python/make_device_deps.sh packs them: the .tar.xz, or the folder it unpacks to
#   (epona-device-deps/). Without it the machine's own headers are used.
# PYTHON: the interpreter (default: python3, else /opt/torch/.venv/bin/python3, the first with
#   numpy and pytest; it needs Python.h too, and pybind11 as its pip package or pybind11-dev).
# EPONA_PY_BUILD: the build folder (default /tmp/epona-py).
# CUDA_ARCH: CMAKE_CUDA_ARCHITECTURES (default 90a, the project's: Hopper with wgmma).
# EPONA_PY_JOBS: build jobs (default every core).
set -euo pipefail
say() { echo "== device_test: $*"; }
die() { echo "device_test: FAILED: $*" >&2; exit 1; }

[[ -f python/epona_module.cpp && -f CMakeLists.txt ]] || die "run it from the repository root"
root=$(pwd)
build=${EPONA_PY_BUILD:-/tmp/epona-py}
arch=${CUDA_ARCH:-90a}
jobs=${EPONA_PY_JOBS:-$(nproc)}
export PATH="$PATH:/usr/local/cuda/bin"

say "checking the machine"
command -v nvcc >/dev/null || die "nvcc not found (PATH or /usr/local/cuda/bin)"
command -v cmake >/dev/null || die "cmake not found"
command -v ninja >/dev/null || die "ninja not found"
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null || say "nvidia-smi gave no GPU"
# The interpreter: PYTHON, else the first of python3 and the machine's venv with NumPy and pytest.
candidates=("${PYTHON:-python3}")
[[ -n ${PYTHON:-} ]] || candidates+=(/opt/torch/.venv/bin/python3)
python=""
for c in "${candidates[@]}"; do
  p=$(command -v "$c" 2>/dev/null) || continue
  "$p" -c "import numpy, pytest" 2>/dev/null && { python=$p; break; }
done
[[ -n $python ]] || die "no interpreter with numpy and pytest among: ${candidates[*]} (set PYTHON)"
"$python" -c "import os, sysconfig; assert os.path.exists(os.path.join(sysconfig.get_paths()['include'], 'Python.h'))" \
  2>/dev/null || die "$python has no Python.h (install python3-dev)"
say "python $python ($("$python" --version 2>&1)), nvcc $(nvcc --version | grep -o 'release [0-9.]*'), arch $arch"

args=(-S "$root" -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DEPONA_PYTHON=ON -DEPONA_CUDA=ON
      -DEPONA_TESTS=OFF -DEPONA_EXAMPLES=OFF -DEPONA_BENCHMARKS=OFF -DCMAKE_CUDA_ARCHITECTURES="$arch"
      -DPython_EXECUTABLE="$python")
# pybind11: the interpreter's pip package, else the system's CMake config (pybind11-dev).
if pybind11_dir=$("$python" -c "import pybind11; print(pybind11.get_cmake_dir())" 2>/dev/null); then
  args+=(-Dpybind11_DIR="$pybind11_dir")
  say "pybind11 from $pybind11_dir"
else
  say "pybind11: no Python package in $python; CMake looks for the system's"
fi
if [[ -n ${EPONA_DEVICE_DEPS:-} ]]; then
  deps=$EPONA_DEVICE_DEPS
  if [[ -f $deps ]]; then
    mkdir -p "$build-deps"
    tar -C "$build-deps" -xJf "$deps" || die "cannot unpack $deps"
    deps=$build-deps/epona-device-deps
  fi
  deps=$(realpath "$deps")
  for need in include/xsimd/xsimd.hpp include/nlohmann/json.hpp include/stb/stb_image.h \
              share/cmake/nlohmann_json/nlohmann_jsonConfig.cmake; do
    [[ -f $deps/$need ]] || die "$deps/$need missing (make the deps with python/make_device_deps.sh)"
  done
  # xsimd by find_path, nlohmann-json by its CMake config, stb by __has_include (include path).
  args+=(-DEPONA_XSIMD_INCLUDE_DIR="$deps/include" -Dnlohmann_json_DIR="$deps/share/cmake/nlohmann_json"
         -DCMAKE_CXX_FLAGS="-isystem $deps/include" -DCMAKE_CUDA_FLAGS="-isystem $deps/include")
  say "headers from $deps"
fi

say "configuring $build"
cmake "${args[@]}" >"$build.configure.log" 2>&1 || { tail -40 "$build.configure.log"; die "configure (log: $build.configure.log)"; }
say "building the module (epona_python) with $jobs jobs: the CUDA unit takes minutes"
start=$(date +%s)
cmake --build "$build" --target epona_python -j "$jobs" || die "build"
say "built in $(( $(date +%s) - start )) s"

# cuBLASLt and cuDNN (cuDNN is opened at run time): the first found, as tests/cuda/device_env.sh.
lt=$(find /usr/local /opt /usr/lib -name 'libcublasLt.so.13' 2>/dev/null | head -1 || true)
dnn=$(find /usr/local /opt /usr/lib -name 'libcudnn.so.9' 2>/dev/null | head -1 || true)
export LD_LIBRARY_PATH="${lt:+$(dirname "$lt"):}${dnn:+$(dirname "$dnn"):}/usr/local/cuda/lib64:${LD_LIBRARY_PATH:-}"
say "cuDNN: ${dnn:-not found (the convolutions use the GEMM engine)}"

export PYTHONPATH="$build/python" EPONA_SOURCE_DIR="$root"
"$python" -c "import epona" || die "the built module does not import (above: why)"
"$python" -c "import epona, sys; sys.exit(0 if epona.cuda_available() else 1)" \
  || die "the module was built but sees no CUDA device (epona.cuda_available() is False): the CUDA tests would only skip"
say "running tests/python"
"$python" -m pytest -q -p no:cacheprovider -rs tests/python || die "tests/python"
say "passed"
