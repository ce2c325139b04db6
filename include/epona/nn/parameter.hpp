// epona/nn/parameter.hpp — the parameter tree. Every layer and block describes its parameters
// once, in `template <class V> void visit_params(const std::string& prefix, V& v)`, calling
//   v.param(name, slot, shape)              for each tensor (slot: the layer's Tensor<T, B> member),
//   visit_stacked(v, parts, shape)          for tensors of one shape kept in one allocation,
//   visit_conv_weight(v, name, slot, shape) for a conv weight (kept in the backend's conv layout),
//   v.counter(name)                         for BatchNorm's `num_batches_tracked`,
// and its sub-modules' visit_params with their prefixes (the official state_dict names).
// Everything that needs the names walks that one description: binding from a weight map
// (ParamBinder), random values (ParamRandomizer), and the list of names and shapes (ParamList:
// parameter counts, random weight maps, `epona info`).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <random>
#include <set>
#include <span>
#include <string>
#include <vector>

#include "epona/core/tensor.hpp"
#include "epona/io/tensor_map.hpp"
#include "epona/nn/backend_context.hpp"
#include "epona/nn/feature_map.hpp"

namespace epona::nn {

// The parameter `name` of `shape` as a backend tensor of T; an empty tensor (and a recorded
// problem) when it is missing or has another shape.
template <class B, class T>
Tensor<T, B> bind_param(io::BindReport& report, const std::string& name, const Shape& shape) {
  const io::RawTensor* raw = report.take(name, shape);
  if (raw == nullptr) return {};
  return BackendTraits<B>::upload(io::to_tensor<T>(*raw));
}

// One of several parameters of one shape kept in one allocation (count, shape...), so that
// layers run as one batched product lie a constant stride apart.
template <class T, class B>
struct StackedPart {
  Tensor<T, B>* slot = nullptr;
  std::string name;
};

// A conv weight [out, in/groups, k, k] (PyTorch) in backend B's layout: unchanged for NCHW
// backends, [out, k, k, in/groups] for channels-last ones (the GEMM's K = (ky, kx, c) order).
template <class B, class T>
Tensor<T, Cpu> conv_weight_layout(Tensor<T, Cpu> w) {
  if constexpr (!channels_last_maps<B>) {
    return w;
  } else {
    EPONA_CHECK(w.dim() == 4 && w.size(2) == w.size(3), "conv weight must be [out, in, k, k], got ", shape_str(w.shape()));
    const std::int64_t O = w.size(0), C = w.size(1), k = w.size(2);
    Tensor<T, Cpu> out({O, k, k, C});
    for (std::int64_t o = 0; o < O; ++o)
      for (std::int64_t c = 0; c < C; ++c)
        for (std::int64_t t = 0; t < k * k; ++t) out.data()[(o * k * k + t) * C + c] = w.data()[(o * C + c) * k * k + t];
    return out;
  }
}

// Parts stacked into one host tensor (count, shape...) and placed in the backend's memory, each
// slot a view of its row: one allocation.
template <class T, class B, class Values>
void stack_into(std::span<const StackedPart<T, B>> parts, const Shape& shape, Values&& values_of) {
  Shape stacked = shape;
  stacked.insert(stacked.begin(), static_cast<std::int64_t>(parts.size()));
  Tensor<T, Cpu> host(stacked);
  for (std::size_t i = 0; i < parts.size(); ++i) {
    const Tensor<T, Cpu> part = values_of(parts[i].name);
    std::copy_n(part.data(), part.numel(), host[static_cast<std::int64_t>(i)].data());
  }
  const Tensor<T, B> all = BackendTraits<B>::upload(host);
  for (std::size_t i = 0; i < parts.size(); ++i) *parts[i].slot = all[static_cast<std::int64_t>(i)];
}

// Fills parameter slots from a weight map; problems (missing, mis-shaped) go to the report.
class ParamBinder {
 public:
  explicit ParamBinder(io::BindReport& report) : report_(report) {}

  template <class T, class B>
  void param(const std::string& name, Tensor<T, B>& slot, const Shape& shape) {
    slot = bind_param<B, T>(report_, name, shape);
  }
  // Every part, or none (each missing or mis-shaped name reported) when any is absent.
  template <class T, class B>
  void stacked(std::span<const StackedPart<T, B>> parts, const Shape& shape) {
    std::vector<const io::RawTensor*> raws;
    for (const auto& p : parts) raws.push_back(report_.take(p.name, shape));
    if (std::find(raws.begin(), raws.end(), nullptr) != raws.end()) {
      for (const auto& p : parts) *p.slot = {};
      return;
    }
    std::size_t next = 0;
    stack_into<T, B>(parts, shape, [&](const std::string&) { return io::to_tensor<T>(*raws[next++]); });
  }
  // A conv weight [out, in/groups, k, k], stored in backend B's conv layout (conv_weight_layout).
  template <class T, class B>
  void conv_weight(const std::string& name, Tensor<T, B>& slot, const Shape& shape) {
    const io::RawTensor* raw = report_.take(name, shape);
    slot = raw ? BackendTraits<B>::upload(conv_weight_layout<B>(io::to_tensor<T>(*raw))) : Tensor<T, B>();
  }
  // BatchNorm's `num_batches_tracked`: an int64 scalar that inference ignores. Absent is fine
  // (PyTorch tolerates that too); present with another type or shape is reported.
  void counter(const std::string& name) {
    const io::TensorMap& map = report_.map();
    if (!map.contains(name)) return;
    counters_.insert(name);
    const io::RawTensor& r = map.at(name);
    if (r.dtype != DType::I64 || r.numel() != 1)
      report_.problem("'" + name + "' should be an int64 scalar, is " + std::string(dtype_name(r.dtype)) + " " +
                      shape_str(r.shape));
  }
  // True for the counters visited so far (to exempt them from a strict report's "unexpected").
  bool is_counter(const std::string& name) const { return counters_.count(name) != 0; }

 private:
  io::BindReport& report_;
  std::set<std::string> counters_;
};

// How large random matrices are: `unit_variance` uniform with variance 1/fan_in (activations stay
// O(1); the DC-AE's convolutions), or `torch_linear` U(±1/sqrt(fan_in)) as PyTorch initialises
// an untrained nn.Linear (the world model's layers; the GPU tests' bf16 bounds were set on it).
enum class WeightInit { unit_variance, torch_linear };

// Seeded random values of a sensible scale for a parameter, by its shape and name: matrices and
// conv weights by the WeightInit; vectors named `weight`, `scale` or `running_var` (norm scales,
// variances) near 1; other vectors (biases, means) near 0 (the spread of vectors halved under
// torch_linear). Values depend only on the seed and the order of the calls, not on the backend.
class RandomValues {
 public:
  explicit RandomValues(std::uint64_t seed, WeightInit init = WeightInit::unit_variance) : rng_(seed), init_(init) {}

  template <class T>
  Tensor<T, Cpu> operator()(const std::string& name, const Shape& shape) {
    Tensor<T, Cpu> host(shape);
    const auto ends_with = [&](const char* s) {
      const std::string suffix(s);
      return name.size() >= suffix.size() && name.compare(name.size() - suffix.size(), suffix.size(), suffix) == 0;
    };
    const bool torch = init_ == WeightInit::torch_linear;
    float center = 0.f, half_width = torch ? 0.05f : 0.1f;
    if (shape.size() != 1) {
      const std::int64_t fan_in = shape.empty() || shape[0] == 0 ? 1 : std::max<std::int64_t>(1, shape_numel(shape) / shape[0]);
      half_width = std::sqrt((torch ? 1.0f : 3.0f) / static_cast<float>(fan_in));
    } else if (ends_with("weight") || ends_with("scale") || ends_with("running_var")) {
      center = 1.f, half_width = torch ? 0.1f : 0.2f;
    }
    // 24 random bits per value -> uniform in [center - half_width, center + half_width): one
    // generator step per value (the real model has 324 M of them).
    constexpr float unit = 1.0f / 16777216.0f;
    for (std::int64_t i = 0; i < host.numel(); ++i) {
      const float u = static_cast<float>(rng_() >> 40) * unit;
      host.data()[i] = T(center + half_width * (2.0f * u - 1.0f));
    }
    return host;
  }

 private:
  std::mt19937_64 rng_;
  WeightInit init_;
};

// Fills parameter slots with RandomValues (benchmarks, tests, examples without a checkpoint).
class ParamRandomizer {
 public:
  explicit ParamRandomizer(std::uint64_t seed) : values_(seed) {}

  template <class T, class B>
  void param(const std::string& name, Tensor<T, B>& slot, const Shape& shape) {
    slot = BackendTraits<B>::upload(values_.template operator()<T>(name, shape));
  }
  template <class T, class B>
  void stacked(std::span<const StackedPart<T, B>> parts, const Shape& shape) {
    stack_into<T, B>(parts, shape, [&](const std::string& name) { return values_.template operator()<T>(name, shape); });
  }
  template <class T, class B>
  void conv_weight(const std::string& name, Tensor<T, B>& slot, const Shape& shape) {
    slot = BackendTraits<B>::upload(conv_weight_layout<B>(values_.template operator()<T>(name, shape)));
  }
  void counter(const std::string&) {}

 private:
  RandomValues values_;
};

// The names and shapes of a module's parameters, in visiting order, without touching its slots:
// parameter counts, random weight maps, listings.
class ParamList {
 public:
  struct Entry {
    std::string name;
    Shape shape;
  };

  template <class T, class B>
  void param(const std::string& name, Tensor<T, B>&, const Shape& shape) {
    entries_.push_back({name, shape});
  }
  void counter(const std::string& name) { counters_.push_back(name); }

  const std::vector<Entry>& entries() const { return entries_; }
  // BatchNorm counters (int64 scalars, not learnable).
  const std::vector<std::string>& counters() const { return counters_; }
  // Values of the parameters whose names start with `prefix` (BatchNorm's running statistics
  // included: they are bound and randomised like the rest).
  double count(const std::string& prefix = "") const {
    return sum(prefix, [](const std::string&) { return true; });
  }
  // Learned values only: BatchNorm's `running_mean` / `running_var` left out (a state_dict's
  // parameters as PyTorch counts them).
  double learned_count(const std::string& prefix = "") const {
    return sum(prefix, [](const std::string& name) { return !is_running_stat(name); });
  }
  // BatchNorm's stored, unlearned elements: running statistics plus one per counter.
  double buffer_count(const std::string& prefix = "") const {
    double n = sum(prefix, is_running_stat);
    for (const auto& c : counters_)
      if (c.compare(0, prefix.size(), prefix) == 0) n += 1;
    return n;
  }
  static bool is_running_stat(const std::string& name) {
    return name.ends_with("running_mean") || name.ends_with("running_var");
  }
  // A float32 weight map holding RandomValues under every name (a checkpoint's stand-in).
  io::TensorMap random_map(std::uint64_t seed, const std::string& source,
                           WeightInit init = WeightInit::unit_variance) const {
    io::TensorMap map(source);
    RandomValues values(seed, init);
    for (const auto& e : entries_) {
      auto data = std::make_shared<Tensor<float, Cpu>>(values.operator()<float>(e.name, e.shape));
      io::RawTensor r;
      r.dtype = DType::F32;
      r.shape = e.shape;
      r.bytes = std::span<const std::byte>(reinterpret_cast<const std::byte*>(data->data()), data->nbytes());
      map.keep_alive(data);
      map.add(e.name, r);
    }
    return map;
  }

 private:
  template <class Keep>
  double sum(const std::string& prefix, Keep keep) const {
    double n = 0;
    for (const auto& e : entries_)
      if (e.name.compare(0, prefix.size(), prefix) == 0 && keep(e.name)) n += double(shape_numel(e.shape));
    return n;
  }

  std::vector<Entry> entries_;
  std::vector<std::string> counters_;
};

// Parameters of one shape in one allocation where the visitor places them (binding,
// randomising), else visited one by one (visitors that only read names and shapes).
template <class V, class T, class B>
void visit_stacked(V& v, std::span<const StackedPart<T, B>> parts, const Shape& shape) {
  if constexpr (requires { v.stacked(parts, shape); }) {
    v.stacked(parts, shape);
  } else {
    for (const auto& p : parts) v.param(p.name, *p.slot, shape);
  }
}

// Routes a conv weight to the visitor's `conv_weight` when it has one (binding, randomising),
// else to its plain `param` (visitors that only read names and shapes).
template <class V, class T, class B>
void visit_conv_weight(V& v, const std::string& name, Tensor<T, B>& slot, const Shape& shape) {
  if constexpr (requires { v.conv_weight(name, slot, shape); })
    v.conv_weight(name, slot, shape);
  else
    v.param(name, slot, shape);
}

// Mixin giving a module (with `template <class V> void visit_params(const std::string&, V&)`)
// the entry points every epona layer has: bind from a weight map, fill with random values, and
// list its parameters.
template <class Derived>
struct Bindable {
  // The report reads `map` (it was made from it); the argument keeps every layer's bind alike.
  void bind(const io::TensorMap&, const std::string& prefix, io::BindReport& report) {
    ParamBinder binder(report);
    static_cast<Derived&>(*this).visit_params(prefix, binder);
  }
  void randomize(std::uint64_t seed, const std::string& prefix = "") {
    ParamRandomizer r(seed);
    static_cast<Derived&>(*this).visit_params(prefix, r);
  }
  ParamList parameters(const std::string& prefix = "") const {
    ParamList list;
    const_cast<Derived&>(static_cast<const Derived&>(*this)).visit_params(prefix, list);  // ParamList writes no slot
    return list;
  }
};

}  // namespace epona::nn
