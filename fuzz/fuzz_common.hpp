// fuzz/fuzz_common.hpp — what every libFuzzer target shares. A reader given arbitrary bytes may
// return a result or throw epona::Error with a message; anything else (another exception type,
// bad_alloc from an unchecked size, an empty message) is a bug, so it aborts and libFuzzer keeps
// the input as a crash artifact. Memory errors, UB and leaks are caught by ASan/UBSan/LSan.
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "epona/core/error.hpp"

// Each target's entry point. tests/reliability/fuzz_replay.cpp includes every target file with
// EPONA_FUZZ_REPLAY defined, which names the entry points fuzz_<target> so that they share one
// program (built by any compiler) that replays the seed corpora and every past finding.
#ifdef EPONA_FUZZ_REPLAY
#define EPONA_FUZZ_TARGET(target) int fuzz_##target(const std::uint8_t* data, std::size_t size)
#else
#define EPONA_FUZZ_TARGET(target) extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size)
#endif

namespace epona_fuzz {

[[noreturn]] inline void bug(const char* what, const char* detail) {
  std::fprintf(stderr, "epona fuzz: %s: %s\n", what, detail);
  std::abort();
}

// EPONA_FUZZ_VERBOSE=1 prints each input's outcome (to see why seeds or a crash input are refused).
inline bool verbose() {
  static const bool on = std::getenv("EPONA_FUZZ_VERBOSE") != nullptr;
  return on;
}

// Runs `body`; accepts a clean return or an epona::Error that says something.
template <class Body>
int run(Body&& body) {
  try {
    body();
    if (verbose()) std::fprintf(stderr, "epona fuzz: accepted\n");
  } catch (const epona::Error& e) {
    if (verbose()) std::fprintf(stderr, "epona fuzz: refused: %s\n", e.what());
    if (std::strlen(e.what()) == 0) bug("epona::Error with an empty message", "");
  } catch (const std::exception& e) {
    bug("an exception other than epona::Error escaped the reader", e.what());
  } catch (...) {
    bug("a non-std exception escaped the reader", "");
  }
  return 0;
}

// A property the fuzz target checks on accepted inputs (round trips); aborts when false.
inline void require(bool ok, const char* what) {
  if (!ok) bug("property violated", what);
}

inline std::span<const std::byte> as_bytes(const std::uint8_t* data, std::size_t size) {
  return {reinterpret_cast<const std::byte*>(data), size};
}
inline std::string_view as_text(const std::uint8_t* data, std::size_t size) {
  return {reinterpret_cast<const char*>(data), size};
}

// Splits a structured input at every occurrence of `separator` (inputs that hold several
// files: a pickle and its storage records, pose.npy and yaw.npy).
inline std::vector<std::string_view> split(std::string_view input, std::string_view separator) {
  std::vector<std::string_view> parts;
  for (std::size_t pos = 0;;) {
    const auto next = input.find(separator, pos);
    parts.push_back(input.substr(pos, next == std::string_view::npos ? std::string_view::npos : next - pos));
    if (next == std::string_view::npos) return parts;
    pos = next + separator.size();
  }
}

}  // namespace epona_fuzz
