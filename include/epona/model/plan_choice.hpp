// epona/model/plan_choice.hpp — one plan out of K hypotheses of a scene
// (WorldModel::plan_hypotheses), and how far they spread. Two rules:
//   medoid: the hypothesis whose summed distance to the others is least (the distance of two plans:
//           their waypoint positions' mean Euclidean distance); a plan the model drew, so its
//           waypoints and headings stay one consistent motion. Ties go to the lower index.
//   mean:   the waypoint-wise mean of x, y and yaw; it minimises the expected L2 error, but between
//           two distinct manoeuvres (a lane change or none) it lies between them.
// docs/evaluation.md compares the two on the evaluation clips.
#pragma once

#include <cmath>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"

namespace epona::model {

enum class PlanChoice { medoid, mean };

inline const char* plan_choice_name(PlanChoice c) { return c == PlanChoice::medoid ? "medoid" : "mean"; }

// The rule of that name; none for any other (the caller's error names where the name came from).
inline std::optional<PlanChoice> plan_choice_named(const std::string& name) {
  for (const PlanChoice c : {PlanChoice::medoid, PlanChoice::mean})
    if (name == plan_choice_name(c)) return c;
  return std::nullopt;
}

// How a planner turns one scene into one plan: K hypotheses and the rule that picks one. K = 1 is the
// official model's single sample. A model may recommend another rule in its configs.json
// ("planner": {"hypotheses": K, "choose": RULE}, read by domain/config_json.hpp), as a model card
// recommends its sampling settings; the bundled model does (docs/evaluation.md says why).
struct PlanningRule {
  std::int64_t hypotheses = 1;
  PlanChoice choose = PlanChoice::medoid;
  bool operator==(const PlanningRule&) const = default;
};

struct PlanFan {
  Tensor<float> hypotheses;             // (K, W, 3) x m, y m, yaw deg
  Tensor<float> chosen;                 // (W, 3)
  std::optional<std::int64_t> chosen_index;  // the medoid's row; none for the mean
  std::vector<double> spread_m;         // per waypoint: RMS distance of the K positions from their mean
};

namespace plan_choice_detail {

// Mean Euclidean distance between the positions of hypotheses a and b.
inline double plan_distance(const Tensor<float>& h, std::int64_t a, std::int64_t b) {
  const std::int64_t W = h.size(1);
  double sum = 0;
  for (std::int64_t w = 0; w < W; ++w)
    sum += std::hypot(double(h.at(a, w, 0)) - h.at(b, w, 0), double(h.at(a, w, 1)) - h.at(b, w, 1));
  return sum / double(W);
}

inline std::int64_t medoid(const Tensor<float>& h) {
  const std::int64_t K = h.size(0);
  std::vector<double> total(static_cast<std::size_t>(K), 0.0);
  for (std::int64_t a = 0; a < K; ++a)
    for (std::int64_t b = a + 1; b < K; ++b) {
      const double d = plan_distance(h, a, b);
      total[a] += d, total[b] += d;
    }
  std::int64_t best = 0;
  for (std::int64_t k = 1; k < K; ++k)
    if (total[k] < total[best]) best = k;
  return best;
}

inline Tensor<float> mean(const Tensor<float>& h) {
  const std::int64_t K = h.size(0), W = h.size(1);
  Tensor<float> out({W, 3});
  for (std::int64_t w = 0; w < W; ++w)
    for (int c = 0; c < 3; ++c) {
      double sum = 0;
      for (std::int64_t k = 0; k < K; ++k) sum += h.at(k, w, c);
      out.at(w, c) = static_cast<float>(sum / double(K));
    }
  return out;
}

inline std::vector<double> spread(const Tensor<float>& h, const Tensor<float>& centre) {
  const std::int64_t K = h.size(0), W = h.size(1);
  std::vector<double> out;
  for (std::int64_t w = 0; w < W; ++w) {
    double sq = 0;
    for (std::int64_t k = 0; k < K; ++k) {
      const double dx = double(h.at(k, w, 0)) - centre.at(w, 0), dy = double(h.at(k, w, 1)) - centre.at(w, 1);
      sq += dx * dx + dy * dy;
    }
    out.push_back(std::sqrt(sq / double(K)));
  }
  return out;
}

}  // namespace plan_choice_detail

// `hypotheses` (K, W, 3), K >= 1, every value finite -> the chosen plan and the fan's spread.
inline PlanFan choose_plan(const Tensor<float>& hypotheses, PlanChoice rule) {
  EPONA_CHECK(hypotheses.dim() == 3 && hypotheses.size(0) >= 1 && hypotheses.size(1) >= 1 && hypotheses.size(2) == 3,
              "plan hypotheses must be (K, W, 3) with K, W >= 1, got ", shape_str(hypotheses.shape()));
  for (std::int64_t i = 0; i < hypotheses.numel(); ++i)
    EPONA_CHECK(std::isfinite(hypotheses.data()[i]), "plan hypothesis ", i / (3 * hypotheses.size(1)),
                " has a non-finite value");
  PlanFan fan;
  fan.hypotheses = hypotheses;
  const Tensor<float> centre = plan_choice_detail::mean(hypotheses);
  if (rule == PlanChoice::medoid) {
    fan.chosen_index = plan_choice_detail::medoid(hypotheses);
    fan.chosen = hypotheses[*fan.chosen_index].clone();
  } else {
    fan.chosen = centre;
  }
  fan.spread_m = plan_choice_detail::spread(hypotheses, centre);
  return fan;
}

}  // namespace epona::model
