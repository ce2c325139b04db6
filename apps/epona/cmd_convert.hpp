// apps/epona/cmd_convert.hpp — `epona convert`: rewrites a checkpoint (the official torch.save
// .pkl, or safetensors) as one safetensors file with the same keys, dtypes and bytes — a flat,
// memory-mappable form that any safetensors reader (and epona, faster) loads without a pickle.
// With --dtype, floating-point tensors are stored in another precision (bfloat16 halves a
// float32 checkpoint), rounded to nearest even; integer tensors are kept.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cmath>
#include <filesystem>
#include <optional>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "activity.hpp"
#include "args.hpp"
#include "console.hpp"
#include "inspect.hpp"
#include "models.hpp"
#include "output_paths.hpp"
#include "epona/core/dtype.hpp"
#include "epona/io/limits.hpp"
#include "epona/io/load_weights.hpp"
#include "epona/io/safetensors.hpp"

namespace epona::app {

inline ArgParser convert_parser() {
  ArgParser p("epona convert", "IN OUT.safetensors [options]",
              "Writes the tensors of a checkpoint (official .pkl or .safetensors) to a safetensors file:\n"
              "same names, dtypes, shapes and bytes. The metadata records the source file name.\n"
              "With --dtype, floating-point tensors are stored in that precision instead (rounded to nearest\n"
              "even; integer tensors such as BatchNorm's num_batches_tracked are kept), and the metadata\n"
              "records the conversion: --dtype bfloat16 halves a float32 checkpoint.");
  p.positionals(2, 2, "input and output files")
      .option("key", "NAME", "state dict inside a .pkl (e.g. model_state_dict, model)", "automatic")
      .option("dtype", "TYPE", "store floating-point tensors as bfloat16, float16 or float32", "as in the input")
      .flag("quiet", "no notes on stderr", 'q')
      .epilog("examples:\n  epona convert dcae_td_20000.pkl dcae_td_20000.safetensors\n"
              "  epona convert epona_nuplan.pkl epona_nuplan-bf16.safetensors --dtype bfloat16");
  return p;
}

// Bytes the tensors view, and the distinct bytes under them (the union of their ranges): a .pkl
// may view one storage through many tensors, which safetensors cannot share, so a 2 MB .pkl of
// 300 views wrote 600 MB. Repeats up to limits::kConvertRepeat x the distinct bytes (tied weights
// are 2x) plus a slack for small buffers are written; more is refused before anything is written.
struct ViewBytes {
  std::uint64_t total = 0, distinct = 0;
};
inline ViewBytes view_bytes(const io::TensorMap& m) {
  std::vector<std::pair<const std::byte*, const std::byte*>> ranges;
  ViewBytes v;
  for (const auto& [name, t] : m.entries()) {
    v.total += t.bytes.size();
    if (!t.bytes.empty()) ranges.emplace_back(t.bytes.data(), t.bytes.data() + t.bytes.size());
  }
  std::sort(ranges.begin(), ranges.end());
  const std::byte* covered = nullptr;  // end of the union so far
  for (const auto& [b, e] : ranges) {
    const std::byte* from = covered && b < covered ? covered : b;
    if (e > from) v.distinct += static_cast<std::uint64_t>(e - from), covered = e;
  }
  return v;
}

inline void check_view_amplification(const io::TensorMap& m, const std::string& in) {
  const ViewBytes v = view_bytes(m);
  const std::uint64_t allowed = io::limits::kConvertRepeat * v.distinct + io::limits::kConvertRepeatSlack;
  EPONA_CHECK(v.total <= allowed, in, ": its tensors view ", v.distinct, " distinct bytes of storage ",
              v.total / std::max<std::uint64_t>(v.distinct, 1), " times over (", v.total,
              " bytes as safetensors, which cannot share storage); convert writes at most ",
              io::limits::kConvertRepeat, "x the distinct bytes. Save the tensors with .clone() to convert them");
}

// ---- --dtype --------------------------------------------------------------------------

inline bool is_floating(DType d) { return d == DType::F32 || d == DType::BF16 || d == DType::F16; }

// The --dtype choice as a DType; nullopt without --dtype (tensors as they are).
inline std::optional<DType> convert_target(const ParsedArgs& a) {
  if (!a.has("dtype")) return std::nullopt;
  const std::string d = a.choice("dtype", {"bfloat16", "bf16", "float16", "fp16", "float32", "fp32"}, "");
  if (d == "bfloat16" || d == "bf16") return DType::BF16;
  if (d == "float16" || d == "fp16") return DType::F16;
  return DType::F32;
}

// One element of a floating-point tensor in dtype `to`, from its float value; a finite value that
// float16 cannot hold (|x| >= 65520 rounds to inf) is refused, naming the tensor and the value:
// the released weights are far below, so such a value means a wrong file or a wrong --dtype.
inline void encode_element(float x, DType to, const std::string& name, std::int64_t index, unsigned char* dst) {
  if (to == DType::F32) return (void)std::memcpy(dst, &x, 4);
  const std::uint16_t bits = to == DType::BF16 ? bf16::from_float(x) : float_to_half(x);
  EPONA_CHECK(to != DType::F16 || !std::isfinite(x) || (bits & 0x7fffu) != 0x7c00u, "tensor '", printable(name, 200),
              "' holds ", x, " (element ", index, "), beyond float16's range (largest 65504): --dtype float16 "
              "would make it inf. Use --dtype bfloat16 (float32's range) or keep float32");
  std::memcpy(dst, &bits, 2);
}

// Writes a floating-point tensor in dtype `to`, converted in chunks (memory stays at one chunk).
inline void write_converted(const std::string& name, const io::RawTensor& t, DType to, io::AtomicFileSink& out) {
  constexpr std::int64_t kChunk = 1 << 16;
  std::vector<unsigned char> buf(static_cast<std::size_t>(kChunk) * dtype_size(to));
  const std::int64_t n = t.numel();
  for (std::int64_t from = 0; from < n; from += kChunk) {
    const std::int64_t count = std::min(kChunk, n - from);
    for (std::int64_t i = 0; i < count; ++i)
      encode_element(load_as_float(t.bytes.data(), t.dtype, static_cast<std::size_t>(from + i)), to, name, from + i,
                     buf.data() + static_cast<std::size_t>(i) * dtype_size(to));
    out.write(buf.data(), static_cast<std::size_t>(count) * dtype_size(to));
  }
}

inline io::SafetensorsEncoding convert_encoding(DType to) {
  return {[to](const std::string&, const io::RawTensor& t) { return is_floating(t.dtype) ? to : t.dtype; },
          [](const std::string& name, const io::RawTensor& t, DType d, io::AtomicFileSink& out) {
            write_converted(name, t, d, out);
          }};
}

// The metadata of a conversion: the dtype the floating-point tensors were stored as, from which
// dtypes, and how many tensors were kept as they were (integers).
inline io::SafetensorsMetadata conversion_metadata(const io::TensorMap& m, DType to) {
  std::set<std::string> from;
  std::int64_t converted = 0, kept = 0;
  for (const auto& [name, t] : m.entries()) {
    if (!is_floating(t.dtype)) ++kept;
    else if (t.dtype != to) ++converted, from.insert(std::string(dtype_name(t.dtype)));
  }
  std::string sources;
  for (const auto& f : from) sources += (sources.empty() ? "" : ", ") + f;
  return {{"dtype", std::string(dtype_name(to))},
          {"dtype_conversion", std::to_string(converted) + " floating-point tensor(s) rounded to nearest even to " +
                                   std::string(dtype_name(to)) + (sources.empty() ? "" : " from " + sources) + "; " +
                                   std::to_string(kept) + " integer tensor(s) kept"}};
}

// Bytes of the output: the input's, with floating-point tensors in `to` when converting.
inline std::uint64_t output_bytes(const io::TensorMap& m, std::optional<DType> to) {
  std::uint64_t b = 0;
  for (const auto& [name, t] : m.entries())
    b += to && is_floating(t.dtype) ? static_cast<std::uint64_t>(t.numel()) * dtype_size(*to) : t.bytes.size();
  return b;
}

inline int run_convert(const ParsedArgs& a, const Console& con) {
  const std::string in = a.positionals()[0], out = a.positionals()[1];
  const std::optional<DType> to = convert_target(a);  // a wrong --dtype is refused before any reading
  check_file(in, "input");
  EPONA_CHECK(std::filesystem::path(out).extension() == ".safetensors", "output ", out,
              ": the name must end in .safetensors");
  std::error_code ec;
  EPONA_CHECK(!std::filesystem::equivalent(in, out, ec), "output ", out, " is the input file");
  prepare_output_file(out, "output " + out);
  con.note("reading ", in);
  const io::TensorMap m = [&] {
    const Activity doing("reading " + in);
    return io::load_weights(in, a.text("key", ""));
  }();
  check_view_amplification(m, in);
  const Activity doing("writing " + out);
  io::SafetensorsMetadata meta = to ? conversion_metadata(m, *to) : io::SafetensorsMetadata{};
  meta["converted_from"] = std::filesystem::path(in).filename().string();
  io::save_safetensors(out, m, meta, to ? convert_encoding(*to) : io::SafetensorsEncoding{});
  const CheckpointStats s = checkpoint_stats(m, 1);
  con.out << "wrote " << out << ": " << s.tensors << " tensors, " << epona::detail::human_bytes(double(output_bytes(m, to)));
  if (to) con.out << " (" << epona::detail::human_bytes(s.bytes) << " before; floating-point tensors as " << dtype_name(*to) << ")";
  con.out << "\n";
  return 0;
}

}  // namespace epona::app
