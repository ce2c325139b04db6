// epona/synth/geometry.hpp — the small geometry the synthetic world shares: planar poses (x, y in
// metres, yaw in radians, counter-clockwise = left), 3-vectors, RGB colours, and the relative
// motion between two poses in Epona's convention (x forward, y left, yaw degrees, left positive).
#pragma once

#include <cmath>
#include <numbers>

namespace epona::synth {

inline constexpr double kPi = std::numbers::pi;
inline double deg(double rad) { return rad * 180.0 / kPi; }
inline double rad(double deg) { return deg * kPi / 180.0; }
inline double wrap_angle(double a) {  // (-pi, pi]
  while (a > kPi) a -= 2 * kPi;
  while (a <= -kPi) a += 2 * kPi;
  return a;
}
inline double clampd(double v, double lo, double hi) { return v < lo ? lo : v > hi ? hi : v; }
inline double lerp(double a, double b, double t) { return a + (b - a) * t; }
inline double smoothstep(double t) {
  t = clampd(t, 0.0, 1.0);
  return t * t * (3 - 2 * t);
}

struct Vec3 {
  double x = 0, y = 0, z = 0;
};
inline Vec3 operator+(Vec3 a, Vec3 b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
inline Vec3 operator-(Vec3 a, Vec3 b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline Vec3 operator*(Vec3 a, double s) { return {a.x * s, a.y * s, a.z * s}; }
inline double dot(Vec3 a, Vec3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline Vec3 cross(Vec3 a, Vec3 b) { return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x}; }
inline Vec3 normalized(Vec3 a) {
  const double n = std::sqrt(dot(a, a));
  return n > 0 ? a * (1.0 / n) : a;
}

struct Rgb {
  float r = 0, g = 0, b = 0;
};
inline Rgb mix(Rgb a, Rgb b, double t) {
  const auto f = static_cast<float>(t);
  return {a.r + (b.r - a.r) * f, a.g + (b.g - a.g) * f, a.b + (b.b - a.b) * f};
}
inline Rgb scaled(Rgb a, double s) {
  const auto f = static_cast<float>(s);
  return {a.r * f, a.g * f, a.b * f};
}
inline Rgb tinted(Rgb a, Rgb t) { return {a.r * t.r, a.g * t.g, a.b * t.b}; }

// A pose on the ground plane: position (m) and heading (rad, counter-clockwise from world +x).
struct Pose2 {
  double x = 0, y = 0, yaw = 0;
};

// Where the world point (px, py) lies in the frame of `p`: x forward, y left.
inline void to_local(const Pose2& p, double px, double py, double& lx, double& ly) {
  const double c = std::cos(p.yaw), s = std::sin(p.yaw), dx = px - p.x, dy = py - p.y;
  lx = c * dx + s * dy;
  ly = -s * dx + c * dy;
}

// Epona's per-frame motion from pose `a` into pose `b`, in the ego frame of `a`.
struct Motion {
  double x = 0, y = 0, yaw_deg = 0;
};
inline Motion motion_between(const Pose2& a, const Pose2& b) {
  Motion m;
  to_local(a, b.x, b.y, m.x, m.y);
  m.yaw_deg = deg(wrap_angle(b.yaw - a.yaw));
  return m;
}

}  // namespace epona::synth
