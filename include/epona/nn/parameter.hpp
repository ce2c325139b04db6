// epona/nn/parameter.hpp — binding one named parameter: look it up in the weight map
// through the BindReport (which records a missing or mis-shaped key instead of stopping at
// the first), convert it to the layer's dtype and place it in the backend's memory.
#pragma once

#include <string>

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

}  // namespace epona::nn
