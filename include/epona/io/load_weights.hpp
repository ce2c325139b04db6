// epona/io/load_weights.hpp — one entry point for weight files: sniffs the first bytes and reads
// an official torch.save checkpoint (ZIP, "PK\x03\x04") or a safetensors file, so the official
// .pkl and a converted .safetensors load the same way. Pre-1.6 (non-ZIP) torch.save files are
// recognised and refused with instructions.
#pragma once

#include <array>
#include <cstring>
#include <fstream>
#include <string>

#include "epona/core/error.hpp"
#include "epona/io/safetensors.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/io/torch_checkpoint.hpp"

namespace epona::io {

enum class WeightFormat { TorchZip, LegacyTorch, Safetensors };

// The format of `path`, from its first bytes (safetensors has no magic: it is the fallback).
inline WeightFormat sniff_weight_format(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  EPONA_CHECK(in.good(), path, ": cannot open the weight file");
  std::array<char, 4> head{};
  in.read(head.data(), head.size());
  if (in.gcount() == 4 && std::memcmp(head.data(), "PK\x03\x04", 4) == 0) return WeightFormat::TorchZip;
  // Legacy torch.save: a protocol-2 pickle of the magic number 0x1950a86a20f9469cfc6c (LONG1, 10 bytes).
  if (in.gcount() == 4 && std::memcmp(head.data(), "\x80\x02\x8a\x0a", 4) == 0) return WeightFormat::LegacyTorch;
  return WeightFormat::Safetensors;
}

// Every tensor of a weight file. For torch checkpoints, `key` picks the state dict (empty:
// automatic, see torch_checkpoint.hpp); safetensors files are flat and take no key.
inline TensorMap load_weights(const std::string& path, const std::string& key = "") {
  switch (sniff_weight_format(path)) {
    case WeightFormat::TorchZip: return load_torch_checkpoint(path, key);
    case WeightFormat::LegacyTorch:
      fail(path,
           ": a legacy (pre-PyTorch-1.6) torch.save file; re-save it with a recent PyTorch "
           "(torch.save(torch.load(path), path2)) or convert it to safetensors");
    case WeightFormat::Safetensors:
      EPONA_CHECK(key.empty(), path, ": a safetensors file is flat, it has no key '", key, "'");
      return load_safetensors(path);
  }
  fail(path, ": unknown weight format");
}

}  // namespace epona::io
