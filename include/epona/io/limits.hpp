// epona/io/limits.hpp — the resource policy: how large an input the readers and the program
// accept. Each limit is sized from the largest legitimate input (the released model at 512x1024,
// rollouts of 600 frames, its checkpoints) with room to spare, and is checked before the work or
// the allocation it bounds. docs/reliability.md ("Resource limits") lists them with their reasons.
#pragma once

#include <cstddef>
#include <cstdint>

namespace epona::io::limits {

// ---- JSON (configs, pose and trajectory files, safetensors headers) ----
// Legitimate files nest at most 4 deep (a list of 4x4 matrices); nlohmann's parser is iterative,
// but anything that walks a value (printing, copying, comparing) recurses once per level.
inline constexpr int kJsonDepth = 64;
// A 600-step trajectory is 27k numbers; a safetensors header of 100k tensors ~1M values.
inline constexpr std::uint64_t kJsonValues = std::uint64_t{1} << 22;
// Keys and string values: tensor names, config names, metadata texts.
inline constexpr std::uint64_t kJsonStringBytes = std::uint64_t{1} << 20;

// ---- CSV (pose and trajectory rows) ----
// Fields past this count are not split (a 96 MB line of commas would be 96M fields).
inline constexpr std::size_t kCsvFields = 16;

// ---- frames and rollouts ----
// Per-frame motions or planned steps read from a file, and frames a rollout may produce: 16x the
// official 600-frame rollout. `generate --max-frames` raises it.
inline constexpr std::int64_t kFrames = 10'000;

// ---- images and latent grids ----
// Pixels of one image or frame (decoded, resized or encoded): 64x the released model's 512x1024.
// `--max-pixels` raises it.
inline constexpr std::int64_t kPixels = std::int64_t{1} << 25;
// One side of an image or of --size: 16384 = 32x the released model's height.
inline constexpr std::int64_t kImageSide = 16384;
// Frames the DC-AE encodes or decodes at their own size (`epona encode`, `epona decode`): 16x the
// released 512x1024, as a configuration's image_size (model/config.hpp). A 5792x5792 PNG, within
// kPixels, took 2.2 GB to encode. `--max-pixels` of encode/decode raises it.
inline constexpr std::int64_t kCodecPixels = std::int64_t{16} * 512 * 1024;

// ---- convert ----
// Tensors viewing one storage are written once each (safetensors cannot share bytes): the output
// may hold the distinct storage bytes this many times (tied weights are 2x), plus a slack.
inline constexpr std::uint64_t kConvertRepeat = 2;
inline constexpr std::uint64_t kConvertRepeatSlack = std::uint64_t{16} << 20;

// ---- compute ----
// --threads: more threads than this many per hardware thread only slow the work down.
inline constexpr int kThreadsPerCore = 4;
inline constexpr int kThreadsCap = 1024;

}  // namespace epona::io::limits
