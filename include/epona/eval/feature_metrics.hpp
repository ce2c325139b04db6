// epona/eval/feature_metrics.hpp — where distribution metrics over learned features plug in:
// FID (Inception-v3 pool features of frames) and FVD (I3D features of clips), as the Epona paper
// reports them. Their feature networks' weights cannot be fetched on these machines, so no
// extractor ships; the evaluation reports each such metric as not computed. An extractor
// implements FeatureExtractor; the distance between the two feature sets is then the Fréchet
// distance of Gaussians fitted to them (Heusel et al. 2017), to be added beside it.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "epona/io/image.hpp"

namespace epona::eval {

// Maps a frame sequence (one frame for FID, a clip for FVD) to one feature vector.
class FeatureExtractor {
 public:
  virtual ~FeatureExtractor() = default;
  virtual std::string name() const = 0;  // "fid", "fvd"
  virtual std::vector<double> features(const std::vector<io::Image>& frames) = 0;
};

// A feature metric's result: a value, or why there is none.
struct FeatureMetric {
  std::string name;
  std::optional<double> value;
  std::string note;
};

// The metrics the paper reports that this build cannot compute.
inline std::vector<FeatureMetric> uncomputed_feature_metrics() {
  const std::string why = "not computed: needs Inception/I3D feature weights, which this build does not ship";
  return {{"fid", std::nullopt, why}, {"fvd", std::nullopt, why}};
}

}  // namespace epona::eval
