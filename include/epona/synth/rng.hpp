// epona/synth/rng.hpp — the synthetic world's own random numbers: splitmix64 to seed, xoshiro256**
// to draw. Every draw is plain integer arithmetic plus one exact scaling to [0, 1), so a seed
// gives the same world on every standard library and compiler (std:: distributions do not).
#pragma once

#include <cstdint>

namespace epona::synth {

inline std::uint64_t splitmix64(std::uint64_t& state) {
  std::uint64_t z = (state += 0x9E3779B97F4A7C15ull);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  return z ^ (z >> 31);
}

// A stateless hash of two words (stream derivation, per-cell texture noise).
inline std::uint64_t hash64(std::uint64_t a, std::uint64_t b) {
  std::uint64_t s = a * 0xD1B54A32D192ED03ull ^ (b + 0x8CB92BA72F3D8DD7ull);
  splitmix64(s);
  return splitmix64(s);
}

class Rng {
 public:
  explicit Rng(std::uint64_t seed) {
    for (auto& w : s_) w = splitmix64(seed);
  }
  // The generator of clip `clip` of run `seed`: independent of how many clips are made.
  static Rng for_clip(std::uint64_t seed, std::uint64_t clip) { return Rng(hash64(seed, clip)); }
  // A child stream (e.g. one per road side), so adding draws to one part leaves the others alone.
  Rng split() { return Rng(next()); }

  std::uint64_t next() {
    const std::uint64_t result = rotl(s_[1] * 5, 7) * 9;
    const std::uint64_t t = s_[1] << 17;
    s_[2] ^= s_[0], s_[3] ^= s_[1], s_[1] ^= s_[2], s_[0] ^= s_[3];
    s_[2] ^= t;
    s_[3] = rotl(s_[3], 45);
    return result;
  }
  double uniform() { return double(next() >> 11) * 0x1.0p-53; }  // [0, 1)
  double uniform(double lo, double hi) { return lo + (hi - lo) * uniform(); }
  // An integer in [0, n), n >= 1 (multiply-shift; the tiny bias is irrelevant here).
  std::int64_t below(std::int64_t n) {
    return static_cast<std::int64_t>((static_cast<unsigned __int128>(next()) * static_cast<std::uint64_t>(n)) >> 64);
  }
  std::int64_t range(std::int64_t lo, std::int64_t hi) { return lo + below(hi - lo + 1); }  // [lo, hi]
  bool chance(double p) { return uniform() < p; }
  double sign() { return chance(0.5) ? 1.0 : -1.0; }

 private:
  static std::uint64_t rotl(std::uint64_t x, int k) { return (x << k) | (x >> (64 - k)); }
  std::uint64_t s_[4];
};

}  // namespace epona::synth
