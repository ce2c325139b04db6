// Tests for epona/model/relative_pose.hpp against torch float32 references written by
// scripts/make_pose_fixtures.py (tests/data/poses/relative_pose.json), a plain float64 loop,
// and hand-made motions that pin the sign conventions. Tolerance: |got - want| <= 1e-5·max(1, |want|).
#include <doctest/doctest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <numbers>

#include <nlohmann/json.hpp>

#include "epona/model/relative_pose.hpp"

using namespace epona;
using nlohmann::json;

namespace {

const json& fixture() {
  static const json j = [] {
    std::ifstream in(std::filesystem::path(EPONA_TEST_DATA_DIR) / "poses" / "relative_pose.json");
    REQUIRE(in.good());
    return json::parse(in);
  }();
  return j;
}

// A nested JSON array -> tensor of its shape (rectangular by construction of the fixture).
template <class T>
Tensor<T> tensor_from(const json& j) {
  Shape shape;
  for (const json* p = &j; p->is_array(); p = &(*p)[0]) shape.push_back(static_cast<std::int64_t>(p->size()));
  Tensor<T> t(shape);
  std::int64_t k = 0;
  auto walk = [&](auto&& self, const json& v) -> void {
    if (v.is_array())
      for (const auto& e : v) self(self, e);
    else
      t.data()[k++] = static_cast<T>(v.get<double>());
  };
  walk(walk, j);
  REQUIRE(k == t.numel());
  return t;
}

double max_scaled_error(const Tensor<float>& got, const Tensor<double>& want) {
  REQUIRE(got.shape() == want.shape());
  double worst = 0;
  for (std::int64_t i = 0; i < got.numel(); ++i)
    worst = std::max(worst, std::fabs(got.data()[i] - want.data()[i]) / std::max(1.0, std::fabs(want.data()[i])));
  return worst;
}

constexpr double kTol = 1e-5;

// Ego-to-world pose: heading `yaw_deg` about z, translation (x, y, z).
Tensor<float> planar_pose(double yaw_deg, double x, double y, double z = 0) {
  const double a = yaw_deg * std::numbers::pi / 180;
  auto m = Tensor<float>::zeros({4, 4});
  m.at(0, 0) = float(std::cos(a)), m.at(0, 1) = float(-std::sin(a));
  m.at(1, 0) = float(std::sin(a)), m.at(1, 1) = float(std::cos(a));
  m.at(2, 2) = 1, m.at(3, 3) = 1;
  m.at(0, 3) = float(x), m.at(1, 3) = float(y), m.at(2, 3) = float(z);
  return m;
}

Tensor<float> stack(std::initializer_list<Tensor<float>> mats) {
  Tensor<float> out({1, std::int64_t(mats.size()), 4, 4});
  std::int64_t i = 0;
  for (const auto& m : mats) std::copy_n(m.data(), 16, out.data() + 16 * i++);
  return out;
}

// float64 reference: general inverse by cofactors, then the section 7 formulas.
std::array<double, 3> reference_motion(const float* from, const float* to) {
  auto R = [](const float* m, int i, int j) { return double(m[i * 4 + j]); };
  double inv[3][3];
  const double det = R(from, 0, 0) * (R(from, 1, 1) * R(from, 2, 2) - R(from, 1, 2) * R(from, 2, 1)) -
                     R(from, 0, 1) * (R(from, 1, 0) * R(from, 2, 2) - R(from, 1, 2) * R(from, 2, 0)) +
                     R(from, 0, 2) * (R(from, 1, 0) * R(from, 2, 1) - R(from, 1, 1) * R(from, 2, 0));
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      const int r0 = (j + 1) % 3, r1 = (j + 2) % 3, c0 = (i + 1) % 3, c1 = (i + 2) % 3;
      inv[i][j] = (R(from, r0, c0) * R(from, r1, c1) - R(from, r0, c1) * R(from, r1, c0)) / det;
    }
  double t[2] = {0, 0}, r00 = 0, r10 = 0;
  for (int k = 0; k < 3; ++k) {
    const double d = R(to, k, 3) - R(from, k, 3);
    t[0] += inv[0][k] * d, t[1] += inv[1][k] * d;
    r00 += inv[0][k] * R(to, k, 0), r10 += inv[1][k] * R(to, k, 0);
  }
  return {t[0], t[1], std::atan2(r10, r00) * 180 / std::numbers::pi};
}

}  // namespace

TEST_CASE("get_rel_pose matches torch float32 (random quaternions, driving and arbitrary 3-D)") {
  const auto abs = tensor_from<float>(fixture()["absolute"]);  // (2, 16, 4, 4)
  const auto rel = model::get_rel_pose(abs);
  const double e_pose = max_scaled_error(rel.pose, tensor_from<double>(fixture()["rel_pose"]));
  const double e_yaw = max_scaled_error(rel.yaw, tensor_from<double>(fixture()["rel_yaw"]));
  MESSAGE("get_rel_pose vs torch: max scaled error pose ", e_pose, ", yaw ", e_yaw);
  CHECK(e_pose <= kTol);
  CHECK(e_yaw <= kTol);
  CHECK(rel.pose.at(0, 0, 0) == 0.f);  // padded entry: no translation at all
  CHECK(rel.pose.at(1, 0, 1) == 0.f);
  CHECK(std::fabs(rel.yaw.at(0, 0, 0)) < 1e-4f);  // R0^-1 R0 = I up to rounding

  // The same from a float64 loop, and from double input (exact fp32 values -> same numbers).
  const std::int64_t N = abs.size(1);
  double worst = 0;
  for (std::int64_t b = 0; b < 2; ++b)
    for (std::int64_t i = 0; i < N; ++i) {
      const auto want = reference_motion(&abs.at(b, std::max<std::int64_t>(i - 1, 0), 0, 0), &abs.at(b, i, 0, 0));
      const double got[3] = {rel.pose.at(b, i, 0), rel.pose.at(b, i, 1), rel.yaw.at(b, i, 0)};
      for (int k = 0; k < 3; ++k) worst = std::max(worst, std::fabs(got[k] - want[k]) / std::max(1.0, std::fabs(want[k])));
    }
  MESSAGE("get_rel_pose vs float64 loop: max scaled error ", worst);
  CHECK(worst <= 1e-4);
  Tensor<double> abs64(abs.shape());
  std::copy_n(abs.data(), abs.numel(), abs64.data());
  const auto rel64 = model::get_rel_pose(abs64);
  CHECK(std::equal(rel64.pose.data(), rel64.pose.data() + rel64.pose.numel(), rel.pose.data()));
  CHECK(std::equal(rel64.yaw.data(), rel64.yaw.data() + rel64.yaw.numel(), rel.yaw.data()));
}

TEST_CASE("get_rel_traj and get_rel_traj_test match torch float32") {
  const auto abs = tensor_from<float>(fixture()["absolute"]);
  const auto& tr = fixture()["traj"];
  const auto F = tr["F"].get<std::int64_t>(), N = tr["N"].get<std::int64_t>();
  const auto traj = model::get_rel_traj(abs, F, N);
  CHECK(traj.pose.shape() == Shape{2, F, N, 2});
  CHECK(max_scaled_error(traj.pose, tensor_from<double>(tr["pose"])) <= kTol);
  CHECK(max_scaled_error(traj.yaw, tensor_from<double>(tr["yaw"])) <= kTol);

  const auto& tt = fixture()["traj_test"];
  const auto test = model::get_rel_traj_test(abs[0], tt["N"].get<std::int64_t>());
  CHECK(test.shape() == Shape{1, 15, 3});
  CHECK(max_scaled_error(test, tensor_from<double>(tt["out"])) <= kTol);
  // Row 0 of the test trajectory is the first per-frame motion.
  const auto rel = model::get_rel_pose(abs);
  CHECK(test.at(0, 0, 0) == rel.pose.at(0, 1, 0));
  CHECK(test.at(0, 0, 2) == rel.yaw.at(0, 1, 0));
}

TEST_CASE("double input keeps precision at nuPlan-scale world coordinates") {
  const auto abs = tensor_from<double>(fixture()["utm"]["absolute"]);  // (12, 4, 4), x ~ 6.6e5, y ~ 4e6
  const auto want = tensor_from<double>(fixture()["utm"]["expected"]);  // (12, 3) float64 reference
  const auto rel = model::get_rel_pose(abs.reshape({1, 12, 4, 4}));
  Tensor<float> got({12, 3});
  for (int i = 0; i < 12; ++i)
    got.at(i, 0) = rel.pose.at(0, i, 0), got.at(i, 1) = rel.pose.at(0, i, 1), got.at(i, 2) = rel.yaw.at(0, i, 0);
  const double err = max_scaled_error(got, want);
  Tensor<float> abs32(abs.shape());
  std::transform(abs.data(), abs.data() + abs.numel(), abs32.data(), [](double v) { return float(v); });
  const auto rel32 = model::get_rel_pose(abs32.reshape({1, 12, 4, 4}));
  double err32 = 0;
  for (int i = 0; i < 12; ++i) err32 = std::max(err32, double(std::fabs(rel32.pose.at(0, i, 0) - want.at(i, 0))));
  MESSAGE("UTM-scale poses: max scaled error from double input ", err, "; fp32 input loses up to ", err32, " m");
  CHECK(err <= kTol);
}

TEST_CASE("sign conventions: x forward, y left, yaw left-positive, in the previous ego frame") {
  // Heading 30 deg; then 2 m forward and 0.5 m left in the car's own frame, turning 10 deg left.
  const double a = 30 * std::numbers::pi / 180;
  const double wx = 100 + 2 * std::cos(a) - 0.5 * std::sin(a), wy = -20 + 2 * std::sin(a) + 0.5 * std::cos(a);
  const auto poses = stack({planar_pose(30, 100, -20), planar_pose(40, wx, wy), planar_pose(25, wx, wy, 1)});
  const auto rel = model::get_rel_pose(poses);
  CHECK(rel.pose.at(0, 1, 0) == doctest::Approx(2).epsilon(1e-5));
  CHECK(rel.pose.at(0, 1, 1) == doctest::Approx(0.5).epsilon(1e-5));
  CHECK(rel.yaw.at(0, 1, 0) == doctest::Approx(10).epsilon(1e-5));
  CHECK(std::fabs(rel.pose.at(0, 2, 0)) < 1e-5f);  // standing still (a z change is dropped) ...
  CHECK(rel.yaw.at(0, 2, 0) == doctest::Approx(-15).epsilon(1e-5));  // ... turning 15 deg right
}

TEST_CASE("the fp32 3x3 inverse pivots and inverts") {
  const model::relpose_detail::Mat3 perm{0, 1, 0, 0, 0, 2, 4, 0, 0};  // needs row exchanges
  const auto inv = model::relpose_detail::inverse3x3(perm);
  const model::relpose_detail::Mat3 want{0, 0, 0.25f, 1, 0, 0, 0, 0.5f, 0};
  CHECK(inv == want);
  const model::relpose_detail::Mat3 m{2, -1, 0.5f, 1e-3f, 3, 1, -2, 0.25f, 4};
  const auto mi = model::relpose_detail::inverse3x3(m);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      double s = 0;
      for (int k = 0; k < 3; ++k) s += double(m[i * 3 + k]) * mi[k * 3 + j];
      CHECK(s == doctest::Approx(i == j).epsilon(1e-6));
    }
}

TEST_CASE("bad poses are named errors") {
  CHECK_THROWS_WITH_AS(model::get_rel_pose(Tensor<float>::zeros({3, 4, 4})), doctest::Contains("(B, N, 4, 4)"), Error);
  CHECK_THROWS_WITH_AS(model::get_rel_pose(Tensor<float>::zeros({1, 2, 3, 4})), doctest::Contains("got (1, 2, 3, 4)"),
                       Error);
  CHECK_THROWS_WITH_AS(model::get_rel_pose(Tensor<float>::zeros({1, 0, 4, 4})), doctest::Contains("at least one"), Error);
  auto singular = stack({planar_pose(0, 0, 0), planar_pose(0, 1, 0)});
  singular.at(0, 0, 2, 2) = 0;  // rotation block of pose 0 loses its z axis
  CHECK_THROWS_WITH_AS(model::get_rel_pose(singular), doctest::Contains("singular"), Error);
  CHECK_THROWS_WITH_AS(model::get_rel_pose(singular), doctest::Contains("from pose 0 to pose 0"), Error);
  auto nan = stack({planar_pose(0, 0, 0), planar_pose(0, 1, 0), planar_pose(0, 2, 0)});
  nan.at(0, 2, 1, 3) = std::numeric_limits<float>::quiet_NaN();
  CHECK_THROWS_WITH_AS(model::get_rel_pose(nan), doctest::Contains("from pose 1 to pose 2"), Error);
  CHECK_THROWS_WITH_AS(model::get_rel_pose(nan), doctest::Contains("non-finite value (nan) at [1, 3]"), Error);
  const auto ok = stack({planar_pose(0, 0, 0), planar_pose(0, 1, 0), planar_pose(0, 2, 0)});
  CHECK_THROWS_WITH_AS(model::get_rel_traj(ok, 2, 2), doctest::Contains("need F+N = 4 frames"), Error);
  CHECK_THROWS_WITH_AS(model::get_rel_traj_test(ok[0], 3), doctest::Contains("needs 4 poses"), Error);
  CHECK_THROWS_WITH_AS(model::get_rel_traj_test(ok, 1), doctest::Contains("(N+1, 4, 4)"), Error);
}
