// epona/io/sha256.hpp — SHA-256 (FIPS 180-4), to check a downloaded checkpoint against the digest
// its publisher lists (the Hugging Face hub shows one for every LFS file). Incremental
// (update/finish) so that a file is hashed by streaming it in blocks: checkpoints reach ~11 GB
// and are never read into memory whole.
#pragma once

#include <algorithm>
#include <array>
#include <cerrno>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <functional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include <unistd.h>

#include "epona/core/error.hpp"
#include "epona/io/read_only_file.hpp"

namespace epona::io {

using Sha256Digest = std::array<std::uint8_t, 32>;

class Sha256 {
 public:
  void update(std::span<const std::byte> bytes) {
    const auto* p = reinterpret_cast<const std::uint8_t*>(bytes.data());
    std::size_t n = bytes.size();
    length_ += n;
    if (used_ > 0) {  // top up a partial block first
      const std::size_t take = std::min(n, kBlock - used_);
      std::memcpy(block_.data() + used_, p, take);
      used_ += take, p += take, n -= take;
      if (used_ < kBlock) return;
      compress(block_.data());
      used_ = 0;
    }
    for (; n >= kBlock; p += kBlock, n -= kBlock) compress(p);
    std::memcpy(block_.data(), p, n);
    used_ = n;
  }
  void update(std::string_view text) { update(std::as_bytes(std::span(text.data(), text.size()))); }

  // The digest of everything given to update(); the object is spent afterwards.
  Sha256Digest finish() {
    const std::uint64_t bits = length_ * 8;
    const std::uint8_t pad = 0x80;
    update(std::as_bytes(std::span(&pad, 1)));
    const std::uint8_t zero[kBlock] = {};
    const std::size_t fill = used_ <= 56 ? 56 - used_ : kBlock + 56 - used_;  // leave 8 bytes for the length
    update(std::as_bytes(std::span(zero, fill)));
    std::uint8_t len[8];
    for (int i = 0; i < 8; ++i) len[i] = static_cast<std::uint8_t>(bits >> (56 - 8 * i));
    update(std::as_bytes(std::span(len, 8)));
    Sha256Digest d{};
    for (int i = 0; i < 8; ++i)
      for (int j = 0; j < 4; ++j) d[4 * i + j] = static_cast<std::uint8_t>(h_[i] >> (24 - 8 * j));
    return d;
  }

 private:
  static constexpr std::size_t kBlock = 64;
  static constexpr std::uint32_t kRound[64] = {
      0x428a2f98, 0x71374491, 0xb5c0fbcf, 0xe9b5dba5, 0x3956c25b, 0x59f111f1, 0x923f82a4, 0xab1c5ed5,
      0xd807aa98, 0x12835b01, 0x243185be, 0x550c7dc3, 0x72be5d74, 0x80deb1fe, 0x9bdc06a7, 0xc19bf174,
      0xe49b69c1, 0xefbe4786, 0x0fc19dc6, 0x240ca1cc, 0x2de92c6f, 0x4a7484aa, 0x5cb0a9dc, 0x76f988da,
      0x983e5152, 0xa831c66d, 0xb00327c8, 0xbf597fc7, 0xc6e00bf3, 0xd5a79147, 0x06ca6351, 0x14292967,
      0x27b70a85, 0x2e1b2138, 0x4d2c6dfc, 0x53380d13, 0x650a7354, 0x766a0abb, 0x81c2c92e, 0x92722c85,
      0xa2bfe8a1, 0xa81a664b, 0xc24b8b70, 0xc76c51a3, 0xd192e819, 0xd6990624, 0xf40e3585, 0x106aa070,
      0x19a4c116, 0x1e376c08, 0x2748774c, 0x34b0bcb5, 0x391c0cb3, 0x4ed8aa4a, 0x5b9cca4f, 0x682e6ff3,
      0x748f82ee, 0x78a5636f, 0x84c87814, 0x8cc70208, 0x90befffa, 0xa4506ceb, 0xbef9a3f7, 0xc67178f2};

  static std::uint32_t rotr(std::uint32_t x, int n) { return (x >> n) | (x << (32 - n)); }

  // One 64-byte block into the state (FIPS 180-4, 6.2.2).
  void compress(const std::uint8_t* p) {
    std::uint32_t w[64];
    for (int t = 0; t < 16; ++t)
      w[t] = std::uint32_t(p[4 * t]) << 24 | std::uint32_t(p[4 * t + 1]) << 16 | std::uint32_t(p[4 * t + 2]) << 8 |
             std::uint32_t(p[4 * t + 3]);
    for (int t = 16; t < 64; ++t) {
      const std::uint32_t s0 = rotr(w[t - 15], 7) ^ rotr(w[t - 15], 18) ^ (w[t - 15] >> 3);
      const std::uint32_t s1 = rotr(w[t - 2], 17) ^ rotr(w[t - 2], 19) ^ (w[t - 2] >> 10);
      w[t] = w[t - 16] + s0 + w[t - 7] + s1;
    }
    std::uint32_t a = h_[0], b = h_[1], c = h_[2], d = h_[3], e = h_[4], f = h_[5], g = h_[6], h = h_[7];
    for (int t = 0; t < 64; ++t) {
      const std::uint32_t t1 = h + (rotr(e, 6) ^ rotr(e, 11) ^ rotr(e, 25)) + ((e & f) ^ (~e & g)) + kRound[t] + w[t];
      const std::uint32_t t2 = (rotr(a, 2) ^ rotr(a, 13) ^ rotr(a, 22)) + ((a & b) ^ (a & c) ^ (b & c));
      h = g, g = f, f = e, e = d + t1, d = c, c = b, b = a, a = t1 + t2;
    }
    const std::uint32_t out[8] = {a, b, c, d, e, f, g, h};
    for (int i = 0; i < 8; ++i) h_[i] += out[i];
  }

  std::uint32_t h_[8] = {0x6a09e667, 0xbb67ae85, 0x3c6ef372, 0xa54ff53a,
                         0x510e527f, 0x9b05688c, 0x1f83d9ab, 0x5be0cd19};
  std::array<std::uint8_t, kBlock> block_{};
  std::size_t used_ = 0;       // bytes waiting in block_
  std::uint64_t length_ = 0;   // bytes given so far
};

// Lowercase hex, as sha256sum and the Hugging Face hub print it.
inline std::string hex(const Sha256Digest& d) {
  static constexpr char kDigits[] = "0123456789abcdef";
  std::string s;
  for (const auto b : d) s += kDigits[b >> 4], s += kDigits[b & 15];
  return s;
}

inline Sha256Digest sha256(std::span<const std::byte> bytes) {
  Sha256 h;
  h.update(bytes);
  return h.finish();
}

// Called after each block of a file: bytes hashed so far and the file's size.
using HashProgress = std::function<void(std::uint64_t done, std::uint64_t total)>;

// The SHA-256 of a file, read in blocks of `block_bytes` (memory stays at one block whatever the
// file's size). Throws epona::Error naming the file and the reason.
inline Sha256Digest sha256_file(const std::string& path, const HashProgress& progress = {},
                                std::size_t block_bytes = std::size_t{4} << 20) {
  const ReadOnlyFile file(path);
  const int fd = file.fd();
  const auto total = static_cast<std::uint64_t>(file.status().st_size);
  std::vector<std::byte> block(std::max<std::size_t>(block_bytes, 1));
  Sha256 h;
  std::uint64_t done = 0;
  for (;;) {
    const ::ssize_t n = ::read(fd, block.data(), block.size());
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) fail(path, ": read error after ", done, " bytes: ", std::strerror(errno));
    if (n == 0) break;
    h.update(std::span(block.data(), static_cast<std::size_t>(n)));
    done += static_cast<std::uint64_t>(n);
    if (progress) progress(done, std::max(total, done));
  }
  return h.finish();
}

}  // namespace epona::io
