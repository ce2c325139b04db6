// epona/synth/render.hpp — a software renderer for the synthetic world's forward camera: a
// pinhole camera ~1.5 m above the road; the ground by casting each sample's ray to the ground
// plane and colouring the hit point by its road coordinates (lanes, dashed and solid markings,
// kerbs, shoulder, grass); everything standing (vehicles, trees, poles, buildings) as flat-shaded
// triangles with a z-buffer; a sky gradient with a sun glow; distance fog towards the horizon
// colour. Rendered at N x N samples per pixel and box-filtered. Rows are independent, so the
// result does not depend on the number of threads.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "epona/io/image.hpp"
#include "epona/synth/geometry.hpp"
#include "epona/synth/road.hpp"
#include "epona/synth/rng.hpp"
#include "epona/synth/scenery.hpp"
#include "epona/synth/traffic.hpp"

namespace epona::synth {

struct Camera {
  int height = 256, width = 512;
  double hfov_deg = 75;        // horizontal field of view
  double horizon = 0.42;       // horizon row as a fraction of the height from the top (no pitch)
  double mount_height = 1.5;   // m above the road
  double focal() const { return 0.5 * width / std::tan(rad(hfov_deg) / 2); }  // pixels
};

struct Lighting {
  Rgb zenith{0.3f, 0.5f, 0.85f}, horizon{0.75f, 0.82f, 0.9f}, sun{1, 0.97f, 0.9f};
  Vec3 sun_dir{0.5, 0.3, 0.8};  // world, towards the sun, unit
  double ambient = 0.45, diffuse = 0.6, brightness = 1.0;
  double fog_distance = 400;   // m: fog weight 1 - exp(-distance / fog_distance)
  double glow = 0.5;           // sun glow strength in the sky
};

struct Palette {
  Rgb asphalt{0.32f, 0.32f, 0.33f}, marking{0.9f, 0.9f, 0.88f}, centre_marking{0.9f, 0.75f, 0.2f};
  Rgb kerb{0.62f, 0.62f, 0.6f}, shoulder{0.45f, 0.42f, 0.38f}, grass{0.28f, 0.42f, 0.16f}, grass2{0.4f, 0.45f, 0.22f};
  double shoulder_width = 1.5;  // m beyond the kerb
  double dash = 3, gap = 9;     // m of a dashed lane line
};

struct Triangle {
  Vec3 a, b, c;  // world, z up
  Rgb colour;    // already shaded
};

// Noise in [-1, 1) of the integer cell (i, j), fixed per world position.
inline double cell_noise(double x, double y, double scale, std::uint64_t salt) {
  const auto i = static_cast<std::int64_t>(std::floor(x * scale)), j = static_cast<std::int64_t>(std::floor(y * scale));
  return double(hash64(static_cast<std::uint64_t>(i) ^ salt, static_cast<std::uint64_t>(j)) >> 11) * 0x1.0p-52 - 1.0;
}

// ---- meshes of the things that stand ---------------------------------------------------------

class Mesh {
 public:
  Mesh(const Lighting& light) : light_(light) {}
  std::vector<Triangle> triangles;

  // A flat-shaded polygon (3 or 4 corners, any winding); `outward` picks the normal's side.
  void face(std::initializer_list<Vec3> corners, Rgb base, Vec3 outward) {
    const Vec3* v = corners.begin();
    Vec3 n = normalized(cross(v[1] - v[0], v[2] - v[0]));
    if (dot(n, outward) < 0) n = n * -1.0;
    const double lit = light_.ambient + light_.diffuse * std::max(0.0, dot(n, light_.sun_dir));
    const Rgb c = scaled(tinted(base, mix(Rgb{1, 1, 1}, light_.sun, std::min(1.0, lit))), lit * light_.brightness);
    triangles.push_back({v[0], v[1], v[2], c});
    if (corners.size() == 4) triangles.push_back({v[0], v[2], v[3], c});
  }

  // A box on pose p: x in [x0, x1], y in [y0, y1] (pose frame), z in [z0, z1]; sides and top.
  void box(const Pose2& p, double x0, double x1, double y0, double y1, double z0, double z1, Rgb side, Rgb top) {
    const double c = std::cos(p.yaw), s = std::sin(p.yaw);
    auto at = [&](double x, double y, double z) { return Vec3{p.x + c * x - s * y, p.y + s * x + c * y, z}; };
    const Vec3 fwd{c, s, 0}, left{-s, c, 0};
    face({at(x1, y0, z0), at(x1, y1, z0), at(x1, y1, z1), at(x1, y0, z1)}, side, fwd);
    face({at(x0, y0, z0), at(x0, y1, z0), at(x0, y1, z1), at(x0, y0, z1)}, side, fwd * -1.0);
    face({at(x0, y1, z0), at(x1, y1, z0), at(x1, y1, z1), at(x0, y1, z1)}, side, left);
    face({at(x0, y0, z0), at(x1, y0, z0), at(x1, y0, z1), at(x0, y0, z1)}, side, left * -1.0);
    face({at(x0, y0, z1), at(x1, y0, z1), at(x1, y1, z1), at(x0, y1, z1)}, top, {0, 0, 1});
  }

  // A car (or van): shadow, dark underbody (reads as wheels), body, glass cabin, lights.
  void vehicle(const Pose2& p, double length, double width, double height, Rgb colour, Rgb shadow) {
    const double l = 0.5 * length, w = 0.5 * width, big = length > 6.5;
    const Rgb glass{0.07f, 0.09f, 0.11f}, dark{0.03f, 0.03f, 0.03f};
    box(p, -l - 0.15, l + 0.15, -w - 0.15, w + 0.15, 0.0, 0.02, shadow, shadow);
    box(p, -l * 0.85, l * 0.85, -w * 0.92, w * 0.92, 0.05, 0.32, dark, dark);
    const double belt = big ? 0.75 * height : 0.6 * height;
    box(p, -l, l, -w, w, 0.3, belt, colour, colour);
    if (big) {
      box(p, l * 0.7, l, -w * 0.97, w * 0.97, belt, height, glass, colour);  // cab windows
      box(p, -l, l * 0.7, -w, w, belt, height, colour, colour);
    } else {
      box(p, -l * 0.55, l * 0.35, -w * 0.86, w * 0.86, belt, height, glass, colour);
    }
    const Rgb red{0.75f, 0.05f, 0.04f}, white{0.95f, 0.93f, 0.8f};
    for (double side : {-1.0, 1.0}) {
      const double y0 = side * w * 0.55, y1 = side * w * 0.9;
      box(p, -l - 0.03, -l + 0.01, std::min(y0, y1), std::max(y0, y1), 0.45 * belt + 0.2, 0.45 * belt + 0.38, red, red);
      box(p, l - 0.01, l + 0.03, std::min(y0, y1), std::max(y0, y1), 0.45 * belt + 0.2, 0.45 * belt + 0.34, white, white);
    }
  }

  void prop(const Prop& q) {
    const double l = 0.5 * q.length, w = 0.5 * q.width;
    switch (q.kind) {
      case PropKind::Tree: {
        const double r = q.crown, top = q.height;
        const bool conifer = (static_cast<std::int64_t>(q.s * 7.0) % 10) < 3;
        const double ring = conifer ? top - 2.6 * r : top - 1.2 * r, bottom = conifer ? ring : ring - 0.9 * r;
        box(q.pose, -l, l, -w, w, 0, bottom + 0.2, q.colour, q.colour);
        const Vec3 c{q.pose.x, q.pose.y, ring};
        for (int k = 0; k < 6; ++k) {
          const double a0 = q.pose.yaw + k * kPi / 3, a1 = a0 + kPi / 3;
          const Vec3 p0{c.x + r * std::cos(a0), c.y + r * std::sin(a0), ring}, p1{c.x + r * std::cos(a1), c.y + r * std::sin(a1), ring};
          const Vec3 out{std::cos(a0 + kPi / 6), std::sin(a0 + kPi / 6), 0};
          const Rgb shade = scaled(q.colour2, 0.92 + 0.16 * ((k * 5) % 3) / 2.0);
          face({p0, p1, Vec3{c.x, c.y, top}}, shade, out + Vec3{0, 0, 0.5});
          face({p0, p1, Vec3{c.x, c.y, bottom}}, shade, out + Vec3{0, 0, -0.5});
        }
        break;
      }
      case PropKind::Pole: {
        box(q.pose, -w, w, -w, w, 0, q.height, q.colour, q.colour);
        if (q.crown != 0) {
          const double y0 = std::min(0.0, q.crown), y1 = std::max(0.0, q.crown);
          box(q.pose, -0.08, 0.08, y0, y1, q.height - 0.15, q.height, q.colour, q.colour);
          const double ye = q.crown;
          box(q.pose, -0.3, 0.3, ye - 0.2, ye + 0.2, q.height - 0.3, q.height - 0.1, q.colour, {0.9f, 0.9f, 0.8f});
        }
        break;
      }
      case PropKind::Building: {
        box(q.pose, -l, l, -w, w, 0, q.height, q.colour, q.colour2);
        // Windows on both long facades: rows every 3.2 m, columns every 3 m.
        const Rgb win = scaled(q.colour2, 0.55);
        for (double side : {-1.0, 1.0}) {
          const double y = side * (w + 0.05);
          for (double z = 1.2; z + 1.4 < q.height; z += 3.2)
            for (double x = -l + 1.2; x + 1.4 < l; x += 3.0) {
              const double c = std::cos(q.pose.yaw), s = std::sin(q.pose.yaw);
              auto at = [&](double px, double pz) { return Vec3{q.pose.x + c * px - s * y, q.pose.y + s * px + c * y, pz}; };
              face({at(x, z), at(x + 1.4, z), at(x + 1.4, z + 1.4), at(x, z + 1.4)}, win, Vec3{-s * side, c * side, 0});
            }
        }
        break;
      }
    }
  }

 private:
  const Lighting& light_;
};

// ---- the renderer ----------------------------------------------------------------------------

struct RenderOptions {
  Camera camera;
  int supersample = 2;  // samples per pixel side
  int threads = 1;
};

namespace render_detail {

struct ScreenTri {
  double ymin, ymax;
  double ea[3], eb[3], ec[3];  // edge functions e(x, y) = ea x + eb y + ec >= 0 inside
  double wa, wb, wc;           // 1/depth = wa x + wb y + wc
  Rgb colour;
};

struct CamVert {
  double depth, x, y;  // forward m; screen sample coordinates
};

}  // namespace render_detail

class Renderer {
 public:
  Renderer(const Road& road, const RoadLayout& layout, const Palette& palette, const Lighting& light, RenderOptions opt)
      : road_(road), layout_(layout), pal_(palette), light_(light), opt_(opt) {
    const int ss = opt_.supersample;
    W_ = opt_.camera.width * ss, H_ = opt_.camera.height * ss;
    f_ = opt_.camera.focal() * ss;
    cx_ = 0.5 * W_, cy_ = opt_.camera.horizon * H_;
  }

  io::Image render(const Pose2& ego, const std::vector<Triangle>& world_tris) const {
    using namespace render_detail;
    std::vector<ScreenTri> tris;
    tris.reserve(world_tris.size());
    for (const Triangle& t : world_tris) add_screen_triangles(ego, t, tris);
    const int ss = opt_.supersample, H = opt_.camera.height, W = opt_.camera.width;
    io::Image img(H, W);
    const double inv = 1.0 / (ss * ss);
#if defined(_OPENMP)
#pragma omp parallel for schedule(dynamic, 4) num_threads(std::max(1, opt_.threads))
#endif
    for (int oy = 0; oy < H; ++oy) {
      std::vector<Rgb> row(static_cast<std::size_t>(W_));
      std::vector<float> acc(static_cast<std::size_t>(W) * 3, 0.0f);
      for (int sy = 0; sy < ss; ++sy) {
        shade_row(ego, tris, oy * ss + sy, row);
        for (int x = 0; x < W_; ++x) {
          float* a = &acc[static_cast<std::size_t>(x / ss) * 3];
          a[0] += row[x].r, a[1] += row[x].g, a[2] += row[x].b;
        }
      }
      for (int x = 0; x < W; ++x)
        for (int c = 0; c < 3; ++c) {
          const double v = clampd(acc[static_cast<std::size_t>(x) * 3 + c] * inv, 0.0, 1.0);
          img.at(oy, x, c) = static_cast<std::uint8_t>(v * 255.0 + 0.5);
        }
    }
    return img;
  }

 private:
  static constexpr double kNear = 0.4, kFarObjects = 600;

  render_detail::CamVert to_camera(const Pose2& ego, const Vec3& p) const {
    double lx, ly;
    to_local(ego, p.x, p.y, lx, ly);
    return {lx, ly, p.z - opt_.camera.mount_height};  // screen coordinates filled by project()
  }
  render_detail::CamVert project(const render_detail::CamVert& c) const {
    return {c.depth, cx_ - f_ * c.x / c.depth, cy_ - f_ * c.y / c.depth};
  }

  // Clips a world triangle to depth >= kNear, projects it and appends its pieces.
  void add_screen_triangles(const Pose2& ego, const Triangle& t, std::vector<render_detail::ScreenTri>& out) const {
    using render_detail::CamVert;
    const CamVert in[3] = {to_camera(ego, t.a), to_camera(ego, t.b), to_camera(ego, t.c)};
    if (in[0].depth > kFarObjects && in[1].depth > kFarObjects && in[2].depth > kFarObjects) return;
    CamVert poly[4];
    int n = 0;
    for (int i = 0; i < 3; ++i) {
      const CamVert& a = in[i];
      const CamVert& b = in[(i + 1) % 3];
      if (a.depth >= kNear) poly[n++] = a;
      if ((a.depth >= kNear) != (b.depth >= kNear)) {
        const double u = (kNear - a.depth) / (b.depth - a.depth);
        poly[n++] = {kNear, lerp(a.x, b.x, u), lerp(a.y, b.y, u)};
      }
    }
    for (int i = 0; i < n; ++i) poly[i] = project(poly[i]);
    for (int i = 1; i + 1 < n; ++i) setup(poly[0], poly[i], poly[i + 1], t.colour, out);
  }

  void setup(const render_detail::CamVert& a, const render_detail::CamVert& b, const render_detail::CamVert& c, Rgb colour,
             std::vector<render_detail::ScreenTri>& out) const {
    const double area = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
    if (!(std::abs(area) > 1e-9)) return;
    const double xmin = std::min({a.x, b.x, c.x}), xmax = std::max({a.x, b.x, c.x});
    const double ymin = std::min({a.y, b.y, c.y}), ymax = std::max({a.y, b.y, c.y});
    if (xmax < 0 || xmin > W_ || ymax < 0 || ymin > H_) return;
    render_detail::ScreenTri t;
    t.ymin = ymin, t.ymax = ymax, t.colour = colour;
    const render_detail::CamVert* v[3] = {&a, &b, &c};
    const double sgn = area > 0 ? 1.0 : -1.0;
    for (int k = 0; k < 3; ++k) {  // edge k from v[k] to v[k+1]: inside on the side of the third vertex
      const auto* p = v[k];
      const auto* q = v[(k + 1) % 3];
      t.ea[k] = -(q->y - p->y) * sgn;
      t.eb[k] = (q->x - p->x) * sgn;
      t.ec[k] = -(t.ea[k] * p->x + t.eb[k] * p->y);
    }
    // 1/depth is affine in screen space: solve the plane through the three vertices.
    const double w0 = 1 / a.depth, w1 = 1 / b.depth, w2 = 1 / c.depth;
    t.wa = ((w1 - w0) * (c.y - a.y) - (w2 - w0) * (b.y - a.y)) / area;
    t.wb = ((w2 - w0) * (b.x - a.x) - (w1 - w0) * (c.x - a.x)) / area;
    t.wc = w0 - t.wa * a.x - t.wb * a.y;
    out.push_back(t);
  }

  Rgb fog(Rgb c, double distance) const {
    return mix(c, light_.horizon, 1.0 - std::exp(-distance / light_.fog_distance));
  }

  void shade_row(const Pose2& ego, const std::vector<render_detail::ScreenTri>& tris, int y,
                 std::vector<Rgb>& row) const {
    const double yc = y + 0.5;
    std::vector<double> best(static_cast<std::size_t>(W_), 0.0);  // 1/depth of the nearest triangle; 0: none
    for (const auto& t : tris) {
      if (yc < t.ymin || yc > t.ymax) continue;
      double lo = 0, hi = W_;
      bool empty = false;
      for (int k = 0; k < 3 && !empty; ++k) {
        const double rest = t.eb[k] * yc + t.ec[k];
        if (t.ea[k] > 0) lo = std::max(lo, -rest / t.ea[k]);
        else if (t.ea[k] < 0) hi = std::min(hi, -rest / t.ea[k]);
        else if (rest < 0) empty = true;
      }
      if (empty || lo > hi) continue;
      const int x0 = std::max(0, static_cast<int>(std::ceil(lo - 0.5))), x1 = std::min(W_ - 1, static_cast<int>(std::floor(hi - 0.5)));
      for (int x = x0; x <= x1; ++x) {
        const double w = t.wa * (x + 0.5) + t.wb * yc + t.wc;
        if (w > best[x]) best[x] = w, row[x] = t.colour;
      }
    }
    const double dy = yc - cy_;
    const double depth = dy > 0 ? opt_.camera.mount_height * f_ / dy : 0;
    const double c = std::cos(ego.yaw), s = std::sin(ego.yaw);
    std::int64_t hint = 0;
    double hint_s = 0, hint_d = 0;
    road_.project(ego.x, ego.y, hint, hint_s, hint_d);
    bool first = true;
    for (int x = 0; x < W_; ++x) {
      const double xc = x + 0.5;
      if (best[x] > 0) {
        const double dz = 1 / best[x];
        row[x] = fog(row[x], dz * std::sqrt(1 + ((xc - cx_) * (xc - cx_) + dy * dy) / (f_ * f_)));
        continue;
      }
      if (dy <= 0 || depth > 5000) {
        row[x] = sky(ego, xc, yc);
        continue;
      }
      const double lat = -(xc - cx_) * depth / f_;
      const double wx = ego.x + c * depth - s * lat, wy = ego.y + s * depth + c * lat;
      if (first) hint += static_cast<std::int64_t>(depth / Road::kStep), first = false;
      double rs, rd;
      road_.project(wx, wy, hint, rs, rd);
      const double dist = std::sqrt(depth * depth + lat * lat);
      row[x] = fog(ground(rs, rd, wx, wy, dist), dist);
    }
  }

  Rgb sky(const Pose2& ego, double xc, double yc) const {
    const double up = (cy_ - yc) / f_, side = (cx_ - xc) / f_;  // per unit forward
    const double elev = std::atan(up / std::sqrt(1 + side * side));
    Rgb c = mix(light_.horizon, light_.zenith, std::sqrt(clampd(elev / 0.7, 0, 1)));
    const double cy = std::cos(ego.yaw), sy = std::sin(ego.yaw);
    const Vec3 ray = normalized({cy - sy * side, sy + cy * side, up});
    const double cosang = dot(ray, light_.sun_dir);
    if (cosang > 0.9) {
      const double g = (cosang - 0.9) / 0.1;
      c = mix(c, light_.sun, std::min(1.0, light_.glow * g * g * g * g + (cosang > 0.9995 ? 1.0 : 0.0)));
    }
    return scaled(c, light_.brightness);
  }

  Rgb ground(double s, double d, double wx, double wy, double dist) const {
    const double lw = layout_.lane_width, R = layout_.right_edge(), L = layout_.left_edge();
    const double lit = light_.brightness * (light_.ambient + light_.diffuse * std::max(0.0, light_.sun_dir.z));
    const Rgb sun = mix(Rgb{1, 1, 1}, light_.sun, 0.7);
    Rgb c;
    if (d >= R && d <= L) {
      const double n = dist < 80 ? 0.03 * cell_noise(wx, wy, 4, 1) : 0.0;
      c = scaled(pal_.asphalt, 1 + n + 0.04 * cell_noise(wx, wy, 0.25, 2));
      const double dash = std::fmod(std::fmod(s, pal_.dash + pal_.gap) + pal_.dash + pal_.gap, pal_.dash + pal_.gap);
      for (int k = 1; k < layout_.lanes; ++k)
        if (std::abs(d + k * lw) < 0.075 && dash < pal_.dash) c = pal_.marking;
      if (d < R + 0.35 && d > R + 0.2) c = pal_.marking;
      if (layout_.oncoming) {
        if (std::abs(std::abs(d) - 0.1) < 0.06) c = pal_.centre_marking;
        if (d > L - 0.35 && d < L - 0.2) c = pal_.marking;
      } else if (d > L - 0.35 && d < L - 0.2) {
        c = pal_.marking;
      }
    } else if (d >= R - layout_.kerb && d <= L + layout_.kerb) {
      c = pal_.kerb;
    } else if (d >= R - layout_.kerb - pal_.shoulder_width && d <= L + layout_.kerb + pal_.shoulder_width) {
      c = scaled(pal_.shoulder, 1 + 0.06 * cell_noise(wx, wy, 2, 3));
    } else {
      const double n = cell_noise(wx, wy, 0.15, 4);
      c = scaled(mix(pal_.grass, pal_.grass2, 0.5 + 0.5 * n), 1 + (dist < 60 ? 0.08 * cell_noise(wx, wy, 2, 5) : 0.0));
    }
    return scaled(tinted(c, sun), lit);
  }

  const Road& road_;
  const RoadLayout& layout_;
  const Palette& pal_;
  const Lighting& light_;
  RenderOptions opt_;
  int W_, H_;
  double f_, cx_, cy_;
};

}  // namespace epona::synth
