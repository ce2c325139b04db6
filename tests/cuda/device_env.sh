# Sourced by the scripts that run prebuilt programs on a GPU machine, after they set BIN (the
# folder with the programs and lib/) and OUT (the log folder): creates OUT, puts the CUDA 13
# libraries (cuBLASLt, cuDNN: the first found on the machine) and BIN/lib on the library path,
# points the tests at the golden data, and defines SAN (compute-sanitizer) and summary (a line
# to stdout and OUT/summary.txt).
mkdir -p "$OUT"
lt=$(find /usr/local /opt /usr/lib -name 'libcublasLt.so.13' 2>/dev/null | head -1)
dnn=$(find /usr/local /opt /usr/lib -name 'libcudnn.so.9' 2>/dev/null | head -1)
export LD_LIBRARY_PATH="$(dirname "${lt:-/usr/local/cuda/lib64/x}"):$(dirname "${dnn:-/usr/local/cuda/lib64/x}"):/usr/local/cuda/lib64:${LD_LIBRARY_PATH:-}:$BIN/lib"
export EPONA_GOLDEN_DIR=${EPONA_GOLDEN_DIR:-$(pwd)/tests/data/golden}
SAN=$(command -v compute-sanitizer || echo /usr/local/cuda/bin/compute-sanitizer)
summary() { echo "$*" | tee -a "$OUT/summary.txt"; }
