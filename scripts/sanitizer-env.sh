# Sourced by scripts/test.sh --sanitize and scripts/test-sanitize.sh: how the sanitizer builds
# run. halt_on_error + abort: a report is a failed test; detect_leaks: LeakSanitizer at exit;
# allocator_may_return_null: an impossible allocation returns null as it does without ASan, so the
# library's own "out of host memory" error is what gets tested (ASan would abort instead).
export ASAN_OPTIONS=${ASAN_OPTIONS:-detect_leaks=1:halt_on_error=1:abort_on_error=1:strict_string_checks=1:detect_stack_use_after_return=1:allocator_may_return_null=1}
export UBSAN_OPTIONS=${UBSAN_OPTIONS:-print_stacktrace=1:halt_on_error=1}
# C++ at -Og: the sanitizers' checks are the same at any level, and -Og compiles the test
# programs in about half the time of -O1 (the sanitized build is most of CI's time on 2 cores;
# docs/reliability.md). The CUDA programs' host code at -O1 (their device code stays optimised).
sanitize_cmake_args=(-DEPONA_SANITIZE=ON "-DCMAKE_CXX_FLAGS_RELEASE=-Og -DNDEBUG" "-DCMAKE_CUDA_FLAGS_RELEASE=-O1 -DNDEBUG")
