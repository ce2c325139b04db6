// epona/nn/parameter.hpp — binding named parameters: look each up in the weight map through
// the BindReport (which records a missing or mis-shaped key instead of stopping at the first),
// convert it to the layer's dtype and place it in the backend's memory (alone, or stacked
// with others of its shape in one allocation).
#pragma once

#include <algorithm>
#include <cstdint>
#include <string>
#include <vector>

#include "epona/core/tensor.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/nn/backend_context.hpp"

namespace epona::nn {

// The parameter `name` of `shape` as a backend tensor of T; an empty tensor (and a recorded
// problem) when it is missing or has another shape.
template <class B, class T>
Tensor<T, B> bind_param(io::BindReport& report, const std::string& name, const Shape& shape) {
  const io::RawTensor* raw = report.take(name, shape);
  if (raw == nullptr) return {};
  return BackendTraits<B>::upload(io::to_tensor<T>(*raw));
}

// The parameters `names`, each of `shape`, stacked into one backend tensor (count, shape...):
// one allocation, so layers that run as one batched product lie a constant stride apart.
// Empty (a problem recorded for each missing or mis-shaped name) when any of them is.
template <class B, class T>
Tensor<T, B> bind_stacked_params(io::BindReport& report, const std::vector<std::string>& names, const Shape& shape) {
  std::vector<const io::RawTensor*> raws;
  for (const auto& name : names) raws.push_back(report.take(name, shape));
  if (std::find(raws.begin(), raws.end(), nullptr) != raws.end()) return {};
  Shape stacked = shape;
  stacked.insert(stacked.begin(), static_cast<std::int64_t>(raws.size()));
  Tensor<T, Cpu> host(stacked);
  for (std::size_t i = 0; i < raws.size(); ++i) {
    const auto part = io::to_tensor<T>(*raws[i]);
    std::copy_n(part.data(), part.numel(), host[static_cast<std::int64_t>(i)].data());
  }
  return BackendTraits<B>::upload(host);
}

}  // namespace epona::nn
