// epona/model/config/problems.hpp — what every configuration's validate() shares: the list of
// its problems (reported all at once) and the limit checks (extents, depth, parameters,
// activations, frame size).
#pragma once

#include <cstdint>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/model/config/constants.hpp"

namespace epona {

namespace detail {
// Collects every problem of a config so that validate() reports them all at once.
class ConfigProblems {
 public:
  explicit ConfigProblems(std::string what) : what_(std::move(what)) {}
  template <class... A>
  void check(bool ok, A&&... parts) {
    if (!ok) list_.push_back(concat(std::forward<A>(parts)...));
  }
  bool ok() const { return list_.empty(); }
  void throw_if_any() const {
    if (list_.empty()) return;
    std::string msg = what_ + ": invalid configuration: ";
    for (std::size_t i = 0; i < list_.size(); ++i) msg += (i ? "; " : "") + list_[i];
    fail(msg);
  }

 private:
  std::string what_;
  std::vector<std::string> list_;
};

// Sizes above this are refused before any product is formed (no int64 overflow anywhere).
inline constexpr std::int64_t max_config_extent = std::int64_t{1} << 24;

inline std::string human_bytes(double b) {
  const char* unit[] = {"B", "KB", "MB", "GB", "TB", "PB", "EB"};
  int u = 0;
  while (b >= 1000.0 && u < 6) b /= 1000.0, ++u;
  std::ostringstream os;
  os.precision(3);
  os << b << ' ' << unit[u];
  return os.str();
}
inline std::string human_count(double n) {
  std::ostringstream os;
  os.precision(3);
  os << n;
  return os.str();
}

// Blocks of one stack (MST, either DiT stream, a DC-AE stage, the temporal front) above this are
// refused: the parameter tree's skeleton (model/parameter_counts.hpp) holds one object per block.
inline constexpr std::int64_t max_config_depth = 256;

// The size limits every model configuration shares, every problem at once: `params` parameters
// (stored at `weight_bytes` each, `weight_type` named in the message), `activations` bytes for
// one `call`, and an image_size h x w (both positive) within constants::max_image_pixels.
// Throws "<what>: invalid configuration: ...".
inline void check_model_size(const char* what, const char* model, double params, double weight_bytes,
                             const char* weight_type, const char* call, double activations, std::int64_t h,
                             std::int64_t w) {
  ConfigProblems p(what);
  p.check(params <= constants::max_parameters, model, " would have ", human_count(params), " parameters (",
          human_bytes(weight_bytes * params), " in ", weight_type, "); the limit is ",
          human_count(constants::max_parameters));
  p.check(activations <= constants::max_activation_bytes, call, " would need about ", human_bytes(activations),
          " of activations; the limit is ", human_bytes(constants::max_activation_bytes));
  p.check(h <= constants::max_image_pixels / w, "image_size (", h, ", ", w, ") is ", h * w,
          " pixels per frame, more than the limit of ", constants::max_image_pixels, " (16x the released 512x1024)");
  p.throw_if_any();
}

}  // namespace detail

}  // namespace epona
