// epona/model/relative_pose.hpp — per-frame ego motions from absolute 4x4 ego-to-world poses
// (utils/preprocess.py `get_rel_pose`, `get_rel_traj`, `get_rel_traj_test`): the pose of frame
// j in the ego frame of frame i, R_i^-1 (t_j - t_i) and atan2 of R_i^-1 R_j, in fp32 like the
// official code (general 3x3 inverse by LU with partial pivoting, as torch.linalg.inv does).
//
// Conventions (follow the numbers of the official data pipeline): the result is in the
// ego frame of the reference pose, nuPlan's x forward, y left, z up; x, y in the pose's length
// unit (metres), yaw in degrees, positive = turning left (counter-clockwise seen from above).
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <numbers>
#include <string>
#include <type_traits>
#include <utility>

#include "epona/core/error.hpp"
#include "epona/core/tensor.hpp"

namespace epona::model {

// Pose of one frame in the ego frame of another: metres, metres, degrees.
struct RelativeMotion {
  float x = 0, y = 0, yaw_deg = 0;
};

namespace relpose_detail {

using Mat3 = std::array<float, 9>;  // row-major

// Inverse of a general 3x3 matrix in fp32: LU factorisation with partial pivoting (multiplying
// by the pivot's reciprocal, as LAPACK's getrf does), then the two triangular solves against the
// identity (getrs). Throws when a pivot is exactly zero, where torch.linalg.inv raises too.
inline Mat3 inverse3x3(Mat3 a) {
  std::array<int, 3> perm{0, 1, 2};
  for (int k = 0; k < 3; ++k) {
    int p = k;
    for (int i = k + 1; i < 3; ++i)
      if (std::fabs(a[i * 3 + k]) > std::fabs(a[p * 3 + k])) p = i;
    EPONA_CHECK(a[p * 3 + k] != 0.0f, "the 3x3 rotation block is singular (not an ego-to-world pose)");
    if (p != k) {
      for (int j = 0; j < 3; ++j) std::swap(a[k * 3 + j], a[p * 3 + j]);
      std::swap(perm[k], perm[p]);
    }
    const float r = 1.0f / a[k * 3 + k];
    for (int i = k + 1; i < 3; ++i) {
      a[i * 3 + k] *= r;
      for (int j = k + 1; j < 3; ++j) a[i * 3 + j] -= a[i * 3 + k] * a[k * 3 + j];
    }
  }
  Mat3 inv{};
  for (int c = 0; c < 3; ++c) {
    std::array<float, 3> b{};
    for (int i = 0; i < 3; ++i) b[i] = perm[i] == c ? 1.0f : 0.0f;
    for (int i = 1; i < 3; ++i)  // L (unit diagonal)
      for (int j = 0; j < i; ++j) b[i] -= a[i * 3 + j] * b[j];
    for (int i = 2; i >= 0; --i) {  // U
      b[i] /= a[i * 3 + i];
      for (int j = 0; j < i; ++j) b[j] -= b[i] * a[j * 3 + i];
    }
    for (int i = 0; i < 3; ++i) inv[i * 3 + c] = b[i];
  }
  return inv;
}

template <class S>
void check_finite_pose(const S* m) {
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c)
      EPONA_CHECK(std::isfinite(m[r * 4 + c]), "non-finite value (", m[r * 4 + c], ") at [", r, ", ", c,
                  "] of a pose matrix");
}

template <class S>
void check_poses(const Tensor<S>& p, int rank, const char* fn, const char* expected) {
  EPONA_CHECK(p.dim() == rank && p.size(-1) == 4 && p.size(-2) == 4, fn, ": expected poses ", expected,
              ", got ", shape_str(p.shape()));
}

template <class S>
const S* pose_at(const Tensor<S>& p, std::int64_t flat_index) {
  return p.data() + flat_index * 16;
}

}  // namespace relpose_detail

// Pose `to` in the ego frame of pose `from` (each a row-major 4x4 [R | t] ego-to-world matrix;
// the bottom row is not read). S = float reproduces the official fp32 numbers; with S = double
// the translation difference is taken in double before rounding to fp32, which equals the fp32
// subtraction for fp32-representable inputs and keeps centimetres at nuPlan's ~1e6 m world
// coordinates where an fp32 subtraction would not.
template <class S>
RelativeMotion relative_motion(const S* from, const S* to) {
  static_assert(std::is_same_v<S, float> || std::is_same_v<S, double>);
  relpose_detail::check_finite_pose(from);
  relpose_detail::check_finite_pose(to);
  relpose_detail::Mat3 r_from, r_to;
  std::array<float, 3> dt;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      r_from[i * 3 + j] = static_cast<float>(from[i * 4 + j]);
      r_to[i * 3 + j] = static_cast<float>(to[i * 4 + j]);
    }
    dt[i] = static_cast<float>(static_cast<double>(to[i * 4 + 3]) - static_cast<double>(from[i * 4 + 3]));
  }
  const auto inv = relpose_detail::inverse3x3(r_from);
  auto row_dot = [&](int row, const float* v, int stride) {  // (inv · v)[row], fp32
    return inv[row * 3] * v[0] + inv[row * 3 + 1] * v[stride] + inv[row * 3 + 2] * v[2 * stride];
  };
  const float r00 = row_dot(0, &r_to[0], 3), r10 = row_dot(1, &r_to[0], 3);  // column 0 of R_rel
  const float yaw_rad = std::atan2(r10, r00);
  return {row_dot(0, dt.data(), 1), row_dot(1, dt.data(), 1),
          (yaw_rad * 180.0f) / static_cast<float>(std::numbers::pi)};
}

// Relative poses in the official tensor layout: pose (..., 2) = (x, y), yaw (..., 1) degrees.
struct RelativePoses {
  Tensor<float> pose, yaw;
};

namespace relpose_detail {
inline RelativePoses allocate(Shape lead) {
  Shape p = lead, y = lead;
  p.push_back(2);
  y.push_back(1);
  return {Tensor<float>(p), Tensor<float>(y)};
}
inline void store(RelativePoses& out, std::int64_t k, const RelativeMotion& m) {
  out.pose.data()[2 * k] = m.x;
  out.pose.data()[2 * k + 1] = m.y;
  out.yaw.data()[k] = m.yaw_deg;
}
// relative_motion with the pose indices in the error message.
template <class S>
RelativeMotion motion_between(const Tensor<S>& p, std::int64_t from, std::int64_t to, const char* fn) {
  try {
    return relative_motion(pose_at(p, from), pose_at(p, to));
  } catch (const Error& e) {
    fail(fn, ": from pose ", from, " to pose ", to, " (flat index over ", shape_str(p.shape()), "): ", e.what());
  }
}
}  // namespace relpose_detail

// get_rel_pose: absolute poses (B, N, 4, 4) -> per-frame motions (B, N, 2), (B, N, 1). The
// sequence is padded by repeating frame 0 in front, so entry 0 is frame 0 seen from itself
// (zero motion up to fp32 rounding of R0^-1 R0) and entry i >= 1 is the motion from frame i-1 to i.
template <class S>
RelativePoses get_rel_pose(const Tensor<S>& poses) {
  relpose_detail::check_poses(poses, 4, "get_rel_pose", "(B, N, 4, 4)");
  const std::int64_t B = poses.size(0), N = poses.size(1);
  EPONA_CHECK(N >= 1, "get_rel_pose: needs at least one pose, got ", shape_str(poses.shape()));
  auto out = relpose_detail::allocate({B, N});
  for (std::int64_t b = 0; b < B; ++b)
    for (std::int64_t i = 0; i < N; ++i)
      relpose_detail::store(out, b * N + i,
                            relpose_detail::motion_between(poses, b * N + std::max<std::int64_t>(i - 1, 0),
                                                           b * N + i, "get_rel_pose"));
  return out;
}

// get_rel_traj (training targets): poses (B, >= F+N, 4, 4) -> (B, F, N, 2), (B, F, N, 1), entry
// (f, n-1) = pose of frame f+n in the ego frame of frame f, n = 1..N.
template <class S>
RelativePoses get_rel_traj(const Tensor<S>& poses, std::int64_t F, std::int64_t N) {
  relpose_detail::check_poses(poses, 4, "get_rel_traj", "(B, F+N, 4, 4)");
  const std::int64_t B = poses.size(0), T = poses.size(1);
  EPONA_CHECK(F >= 1 && N >= 1 && F + N <= T, "get_rel_traj: F = ", F, " origins and N = ", N,
              " steps need F+N = ", F + N, " frames, got ", shape_str(poses.shape()));
  auto out = relpose_detail::allocate({B, F, N});
  for (std::int64_t b = 0; b < B; ++b)
    for (std::int64_t f = 0; f < F; ++f)
      for (std::int64_t n = 1; n <= N; ++n)
        relpose_detail::store(out, (b * F + f) * N + n - 1,
                              relpose_detail::motion_between(poses, b * T + f, b * T + f + n, "get_rel_traj"));
  return out;
}

// get_rel_traj_test: poses (>= N+1, 4, 4) -> (1, N, 3) = (x, y, yaw°) of frames 1..N relative
// to frame 0 (what a predicted trajectory is compared with).
template <class S>
Tensor<float> get_rel_traj_test(const Tensor<S>& poses, std::int64_t N) {
  relpose_detail::check_poses(poses, 3, "get_rel_traj_test", "(N+1, 4, 4)");
  EPONA_CHECK(N >= 1 && N + 1 <= poses.size(0), "get_rel_traj_test: N = ", N, " needs ", N + 1,
              " poses, got ", shape_str(poses.shape()));
  Tensor<float> out({1, N, 3});
  for (std::int64_t n = 1; n <= N; ++n) {
    const auto m = relpose_detail::motion_between(poses, 0, n, "get_rel_traj_test");
    out.at(0, n - 1, 0) = m.x;
    out.at(0, n - 1, 1) = m.y;
    out.at(0, n - 1, 2) = m.yaw_deg;
  }
  return out;
}

}  // namespace epona::model
