// epona/nn/linear_shards.hpp — one shard's weights of a tensor-parallel model, cut from the whole
// model's weight map (core/tensor_parallel.hpp). A Linear split on its outputs keeps its shard's
// rows of W and b (Megatron's column-parallel layer); one split on its inputs keeps its shard's
// columns of W, and the bias on shard 0 only, as the shards' partial outputs are summed (the
// row-parallel layer). A split dimension may be several segments split alike: a fused [q | k | v]
// projection gives each shard its heads of q, of k and of v. The result binds as any weight map.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <map>
#include <memory>
#include <numeric>
#include <span>
#include <string>
#include <vector>

#include "epona/core/dtype.hpp"
#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"
#include "epona/core/tensor_parallel.hpp"
#include "epona/io/tensor_map.hpp"

namespace epona::nn {

// How one Linear layer (weights `<prefix>weight` (out, in), `<prefix>bias` (out)) is split.
struct LinearSplit {
  enum Side { outputs, inputs };
  std::string prefix;
  Side side = outputs;
  std::vector<std::int64_t> segments;  // the split dimension as consecutive segments, each split evenly
};

namespace detail {
// [begin, end) runs of the split dimension that `shard` keeps, in order.
inline std::vector<std::pair<std::int64_t, std::int64_t>> kept_runs(const LinearSplit& split, const TensorShard& shard,
                                                                    const std::string& name, std::int64_t extent) {
  const std::int64_t total = std::accumulate(split.segments.begin(), split.segments.end(), std::int64_t{0});
  EPONA_CHECK(total == extent, "tensor-parallel split of '", name, "': its dimension has ", extent,
              " entries, the model's widths give ", total);
  std::vector<std::pair<std::int64_t, std::int64_t>> runs;
  std::int64_t offset = 0;
  for (const std::int64_t len : split.segments) {
    EPONA_CHECK(len % shard.size == 0, "tensor-parallel split of '", name, "': a segment of ", len,
                " entries does not split over ", shard.size, " shards");
    runs.emplace_back(offset + shard.part_begin(len), offset + shard.part_end(len));
    offset += len;
  }
  return runs;
}

struct OwnedBytes {
  std::vector<std::byte> bytes;
};
}  // namespace detail

// The weight map of shard `shard`: every tensor of `full` as it is, but the weights and biases
// of `splits`, cut. Tensors of `full` stay where they lie (the result keeps `full`'s memory alive).
inline io::TensorMap shard_weights(const io::TensorMap& full, const std::vector<LinearSplit>& splits,
                                   const TensorShard& shard) {
  shard.check("shard_weights");
  io::TensorMap out(full.source() + " (shard " + std::to_string(shard.rank) + " of " + std::to_string(shard.size) + ")");
  out.keep_alive(std::make_shared<io::TensorMap>(full));
  std::map<std::string, io::RawTensor> cut;
  const auto store = [&](const std::string& name, DType dtype, Shape shape, std::vector<std::byte> bytes) {
    auto owned = std::make_shared<detail::OwnedBytes>(detail::OwnedBytes{std::move(bytes)});
    cut[name] = io::RawTensor{dtype, std::move(shape), std::span<const std::byte>(owned->bytes)};
    out.keep_alive(owned);
  };
  for (const auto& split : splits) {
    const std::string wname = split.prefix + "weight", bname = split.prefix + "bias";
    if (!full.contains(wname)) continue;  // binding reports it missing
    const io::RawTensor& w = full.at(wname);
    EPONA_CHECK(w.shape.size() == 2, "tensor-parallel split of '", wname, "': a Linear weight is (out, in), got ",
                shape_str(w.shape));
    const std::int64_t rows = w.shape[0], cols = w.shape[1];
    const std::size_t es = dtype_size(w.dtype);
    const bool by_rows = split.side == LinearSplit::outputs;
    const auto runs = detail::kept_runs(split, shard, wname, by_rows ? rows : cols);
    std::int64_t kept = 0;
    for (const auto& [b, e] : runs) kept += e - b;
    std::vector<std::byte> bytes;
    bytes.reserve(static_cast<std::size_t>(kept * (by_rows ? cols : rows)) * es);
    const auto append = [&](std::int64_t from, std::int64_t count) {
      const std::byte* p = w.bytes.data() + static_cast<std::size_t>(from) * es;
      bytes.insert(bytes.end(), p, p + static_cast<std::size_t>(count) * es);
    };
    if (by_rows) {
      for (const auto& [b, e] : runs) append(b * cols, (e - b) * cols);
    } else {
      for (std::int64_t r = 0; r < rows; ++r)
        for (const auto& [b, e] : runs) append(r * cols + b, e - b);
    }
    store(wname, w.dtype, by_rows ? Shape{kept, cols} : Shape{rows, kept}, std::move(bytes));
    if (!full.contains(bname)) continue;
    const io::RawTensor& bias = full.at(bname);
    EPONA_CHECK(bias.shape == Shape{rows}, "tensor-parallel split of '", bname, "': a bias of ", rows,
                " entries, got ", shape_str(bias.shape));
    const std::size_t bs = dtype_size(bias.dtype);
    std::vector<std::byte> b;
    if (by_rows) {
      for (const auto& [from, to] : runs) {
        const std::byte* p = bias.bytes.data() + static_cast<std::size_t>(from) * bs;
        b.insert(b.end(), p, p + static_cast<std::size_t>(to - from) * bs);
      }
    } else {
      // Added once to the sum: shard 0 keeps it, the others add zeros (all-zero bytes are 0 in
      // every floating-point dtype).
      b.assign(bias.bytes.begin(), bias.bytes.end());
      if (shard.rank != 0) std::fill(b.begin(), b.end(), std::byte{0});
    }
    store(bname, bias.dtype, by_rows ? Shape{kept} : Shape{rows}, std::move(b));
  }
  for (const auto& [name, t] : full.entries()) out.add(name, cut.count(name) ? cut.at(name) : t);
  return out;
}

}  // namespace epona::nn
