// epona/io/jpeg_scan.hpp — checks that every scan of a sequential (baseline or extended) Huffman
// JPEG holds all the blocks its frame header declares. stb_image feeds zeros once a scan's data
// runs into a marker, so a file cut short mid-scan that still ends with an end-of-image marker
// decodes "successfully" into a partly grey image; this walks the entropy-coded data (Huffman
// codes only: no dequantisation, no IDCT) and counts the blocks decoded before the data ends.
// Progressive and arithmetic-coded files are left to stb (their scans refine, so a count of
// blocks says little). Work is linear in the file.
#pragma once

#include <algorithm>
#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "epona/core/error.hpp"

namespace epona::io {

namespace jpeg_detail {

struct Huffman {
  bool present = false;
  std::array<int, 17> maxcode{}, valptr{}, mincode{};  // per code length 1..16 (JPEG F.2.2.3)
  std::vector<std::uint8_t> values;
};

inline Huffman make_table(std::span<const std::uint8_t> counts, std::span<const std::uint8_t> values) {
  Huffman h;
  h.present = true;
  h.values.assign(values.begin(), values.end());
  int code = 0, k = 0;
  for (int len = 1; len <= 16; ++len) {
    const int n = counts[len - 1];
    h.valptr[len] = k;
    h.mincode[len] = code;
    code += n;
    k += n;
    h.maxcode[len] = n ? code - 1 : -1;
    code <<= 1;
  }
  return h;
}

// Reads the entropy-coded bits of one scan: 0xFF00 is a data 0xFF, RSTn are handled by the
// caller, any other marker ends the data (reading past it sets `ended`).
class BitReader {
 public:
  BitReader(std::span<const std::uint8_t> b, std::size_t pos) : b_(b), pos_(pos) {}
  int bit() {
    if (nbits_ == 0 && !fill()) return ended_ = true, 0;
    --nbits_;
    return (byte_ >> nbits_) & 1;
  }
  int bits(int n) {
    int v = 0;
    for (int i = 0; i < n; ++i) v = (v << 1) | bit();
    return v;
  }
  bool ended() const { return ended_; }
  // At a restart interval: drop the rest of the byte and step over an RSTn marker.
  bool restart() {
    nbits_ = 0;
    while (pos_ + 2 < b_.size() && b_[pos_] == 0xFF && b_[pos_ + 1] == 0xFF) ++pos_;  // fill bytes
    if (pos_ + 1 < b_.size() && b_[pos_] == 0xFF && b_[pos_ + 1] >= 0xD0 && b_[pos_ + 1] <= 0xD7) {
      pos_ += 2;
      return true;
    }
    return false;
  }
  // Where the markers after the scan begin (past the scan's last data byte).
  std::size_t end_position() const { return pos_; }

 private:
  bool fill() {
    if (pos_ >= b_.size()) return false;
    if (b_[pos_] == 0xFF) {
      if (pos_ + 1 >= b_.size() || b_[pos_ + 1] != 0x00) return false;  // a marker: the data ends
      byte_ = 0xFF, pos_ += 2;
    } else {
      byte_ = b_[pos_++];
    }
    nbits_ = 8;
    return true;
  }
  std::span<const std::uint8_t> b_;
  std::size_t pos_;
  int byte_ = 0, nbits_ = 0;
  bool ended_ = false;
};

// The symbol of the next Huffman code, or -1 (no such code: corrupt, left to stb).
inline int decode(BitReader& r, const Huffman& h) {
  int code = 0;
  for (int len = 1; len <= 16; ++len) {
    code = (code << 1) | r.bit();
    if (h.maxcode[len] >= code && code >= h.mincode[len]) {
      const int k = h.valptr[len] + code - h.mincode[len];
      return k < static_cast<int>(h.values.size()) ? h.values[static_cast<std::size_t>(k)] : -1;
    }
  }
  return -1;
}

// One 8x8 block's codes; false when the codes make no sense (corrupt, left to stb).
inline bool skip_block(BitReader& r, const Huffman& dc, const Huffman& ac) {
  const int s = decode(r, dc);
  if (s < 0 || s > 16) return false;
  r.bits(s);
  for (int k = 1; k < 64;) {
    const int rs = decode(r, ac);
    if (rs < 0) return false;
    const int run = rs >> 4, size = rs & 15;
    if (size == 0) {
      if (run != 15) break;  // end of block
      k += 16;
      continue;
    }
    k += run;
    r.bits(size);
    ++k;
  }
  return true;
}

struct Component {
  int id = 0, h = 1, v = 1;
};

}  // namespace jpeg_detail

// Throws when a sequential Huffman scan ends before its last block; returns quietly for anything
// it does not model (progressive, arithmetic coding, odd structure: stb decides those).
inline void check_jpeg_scans_complete(std::span<const std::uint8_t> b, const std::string& source) {
  using namespace jpeg_detail;
  std::array<Huffman, 4> dc, ac;
  std::vector<Component> comps;
  std::int64_t width = 0, height = 0;
  int hmax = 1, vmax = 1, restart_interval = 0, scan_no = 0;
  bool sequential = false;
  for (std::size_t pos = 2; pos + 3 < b.size();) {
    if (b[pos] != 0xFF) {  // bytes between segments: stb skips to the next 0xFF, and so does this walk
      ++pos;
      continue;
    }
    const std::uint8_t m = b[pos + 1];
    if (m == 0xFF) {
      ++pos;
      continue;
    }
    if (m == 0xD9) return;  // end of image
    const std::size_t len = (std::size_t{b[pos + 2]} << 8) | b[pos + 3];
    if (len < 2 || pos + 2 + len > b.size()) return;
    const std::span<const std::uint8_t> seg = b.subspan(pos + 4, len - 2);
    if (m == 0xC0 || m == 0xC1) {  // SOF0/SOF1: sequential Huffman
      if (seg.size() < 6) return;
      height = (seg[1] << 8) | seg[2], width = (seg[3] << 8) | seg[4];
      const int n = seg[5];
      if (seg.size() < 6 + 3 * std::size_t(n) || height == 0 || width == 0) return;
      for (int i = 0; i < n; ++i) {
        const Component c{seg[6 + 3 * i], seg[7 + 3 * i] >> 4, seg[7 + 3 * i] & 15};
        if (c.h < 1 || c.h > 4 || c.v < 1 || c.v > 4) return;
        hmax = std::max(hmax, c.h), vmax = std::max(vmax, c.v);
        comps.push_back(c);
      }
      sequential = true;
    } else if ((m >= 0xC2 && m <= 0xCF && m != 0xC4 && m != 0xC8 && m != 0xCC)) {
      return;  // progressive, lossless or arithmetic: not modelled
    } else if (m == 0xC4) {  // DHT
      for (std::size_t t = 0; t + 17 <= seg.size();) {
        std::size_t codes = 0;
        for (int i = 1; i <= 16; ++i) codes += seg[t + i];
        if (t + 17 + codes > seg.size() || (seg[t] & 15) > 3) return;
        auto& table = (seg[t] >> 4) ? ac[seg[t] & 15] : dc[seg[t] & 15];
        table = make_table(seg.subspan(t + 1, 16), seg.subspan(t + 17, codes));
        t += 17 + codes;
      }
    } else if (m == 0xDD) {  // DRI
      if (seg.size() < 2) return;
      restart_interval = (seg[0] << 8) | seg[1];
    } else if (m == 0xDA) {  // SOS: walk the scan
      if (!sequential || seg.empty()) return;
      ++scan_no;
      const int ns = seg[0];
      if (ns < 1 || seg.size() < 1 + 2 * std::size_t(ns)) return;
      std::vector<std::pair<const Component*, int>> in_scan;  // component, table byte
      for (int i = 0; i < ns; ++i) {
        const Component* c = nullptr;
        for (const auto& x : comps)
          if (x.id == seg[1 + 2 * i]) c = &x;
        const int tables = seg[2 + 2 * i];
        if (!c || (tables >> 4) > 3 || (tables & 15) > 3) return;  // stb refuses these itself
        // stb decodes with whatever an undefined table holds (finding 12 of docs/reliability.md).
        EPONA_CHECK(dc[tables >> 4].present && ac[tables & 15].present, source, ": corrupt JPEG (scan ", scan_no,
                    " codes component ", c->id, " with Huffman tables DC ", tables >> 4, " and AC ", tables & 15,
                    ", and the file does not define ", dc[tables >> 4].present ? "the AC one" : "the DC one", ")");
        in_scan.emplace_back(c, tables);
      }
      // Blocks per MCU and MCU count: interleaved scans cover the frame in hmax x vmax MCUs;
      // a one-component scan walks that component's own blocks (JPEG A.2).
      std::int64_t mcus = 0;
      if (ns == 1) {
        const auto* c = in_scan[0].first;
        const std::int64_t cw = (width * c->h + hmax - 1) / hmax, ch = (height * c->v + vmax - 1) / vmax;
        mcus = ((cw + 7) / 8) * ((ch + 7) / 8);
      } else {
        mcus = ((width + 8 * hmax - 1) / (8 * hmax)) * ((height + 8 * vmax - 1) / (8 * vmax));
      }
      BitReader r(b, pos + 2 + len);
      for (std::int64_t mcu = 0; mcu < mcus; ++mcu) {
        const bool at_restart = restart_interval > 0 && mcu > 0 && mcu % restart_interval == 0;
        EPONA_CHECK(!at_restart || r.restart(), source, ": truncated JPEG (scan ", scan_no, " ends after ", mcu,
                    " of ", mcus, " MCUs of its ", height, "x", width, " image, at a restart interval)");
        for (const auto& [c, tables] : in_scan) {
          const int blocks = ns == 1 ? 1 : c->h * c->v;
          for (int k = 0; k < blocks; ++k)
            EPONA_CHECK(skip_block(r, dc[tables >> 4], ac[tables & 15]), source, ": corrupt JPEG (scan ", scan_no,
                        ", MCU ", mcu, " of ", mcus, ": a code its Huffman tables do not hold)");
        }
        EPONA_CHECK(!r.ended(), source, ": truncated JPEG (scan ", scan_no, " ends after ", mcu, " of ", mcus,
                    " MCUs of its ", height, "x", width, " image; the rest would decode as grey)");
      }
      // Step to the marker after the scan data (not a stuffed 0xFF00, not an RSTn).
      const auto is_marker = [&](std::size_t i) {
        return b[i] == 0xFF && b[i + 1] != 0x00 && (b[i + 1] < 0xD0 || b[i + 1] > 0xD7);
      };
      std::size_t next = r.end_position();
      while (next + 1 < b.size() && !is_marker(next)) ++next;
      pos = next;
      continue;
    }
    pos += 2 + len;
  }
}

}  // namespace epona::io
