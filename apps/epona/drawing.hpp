// apps/epona/drawing.hpp — pictures the program writes besides the frames: a planned trajectory
// drawn top-down over the last input frame (plan.png), and a contact sheet of input and
// generated frames, each tile numbered. Plain drawing into the RGB buffer (discs along
// segments), digits from a built-in 5x7 bitmap font.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <string>
#include <vector>

#include "epona/core/tensor.hpp"
#include "epona/io/image.hpp"

namespace epona::app {

using Rgb = std::array<std::uint8_t, 3>;

inline void fill_disc(io::Image& img, double cx, double cy, double radius, Rgb colour) {
  const auto y0 = static_cast<std::int64_t>(std::floor(cy - radius)), y1 = static_cast<std::int64_t>(std::ceil(cy + radius));
  const auto x0 = static_cast<std::int64_t>(std::floor(cx - radius)), x1 = static_cast<std::int64_t>(std::ceil(cx + radius));
  for (std::int64_t y = std::max<std::int64_t>(y0, 0); y <= std::min(y1, img.height - 1); ++y)
    for (std::int64_t x = std::max<std::int64_t>(x0, 0); x <= std::min(x1, img.width - 1); ++x) {
      const double dx = double(x) - cx, dy = double(y) - cy;
      if (dx * dx + dy * dy <= radius * radius + 0.25)
        for (int c = 0; c < 3; ++c) img.at(y, x, c) = colour[c];
    }
}

// A segment of the given half-width: discs every half pixel along it (clipped to the image).
inline void draw_segment(io::Image& img, double x0, double y0, double x1, double y1, double radius, Rgb colour) {
  const double length = std::hypot(x1 - x0, y1 - y0);
  const int n = std::max(1, static_cast<int>(std::ceil(length * 2)));
  for (int i = 0; i <= n; ++i) {
    const double t = double(i) / n;
    fill_disc(img, x0 + (x1 - x0) * t, y0 + (y1 - y0) * t, radius, colour);
  }
}

inline void draw_rect_outline(io::Image& img, std::int64_t top, std::int64_t left, std::int64_t h, std::int64_t w,
                              int thickness, Rgb colour) {
  for (std::int64_t y = top; y < top + h; ++y)
    for (std::int64_t x = left; x < left + w; ++x) {
      const bool edge = y < top + thickness || y >= top + h - thickness || x < left + thickness || x >= left + w - thickness;
      if (edge && y >= 0 && y < img.height && x >= 0 && x < img.width)
        for (int c = 0; c < 3; ++c) img.at(y, x, c) = colour[c];
    }
}

// ---- plan.png: top-down projection over the frame -------------------------------------
//
// The ego car sits at the bottom centre, 5% of the height above the lower edge; forward (+x)
// points up, left (+y) points left, both axes share one scale (pixels per metre) chosen so the
// plan fits: the furthest forward reach (at least 10 m) spans 85% of the height and the widest
// lateral offset (at least 1 m) at most 45% of the width. This is a bird's-eye sketch laid over
// the camera image, not a projection into it (the camera's intrinsics are not known).
struct TopDownView {
  double origin_x = 0, origin_y = 0;  // ego position in pixels
  double pixels_per_metre = 1;

  static TopDownView fit(const io::Image& frame, const Tensor<float>& waypoints) {  // (W, 3)
    double reach = 10.0, lateral = 1.0;
    for (std::int64_t i = 0; i < waypoints.size(0); ++i) {
      reach = std::max(reach, double(waypoints.at(i, 0)));
      lateral = std::max(lateral, std::abs(double(waypoints.at(i, 1))));
    }
    TopDownView v;
    v.origin_x = double(frame.width) / 2.0;
    v.origin_y = double(frame.height - 1) - std::round(0.05 * double(frame.height));
    v.pixels_per_metre = std::min(0.85 * double(frame.height) / reach, 0.45 * double(frame.width) / lateral);
    return v;
  }
  double px(double /*x_fwd*/, double y_left) const { return origin_x - y_left * pixels_per_metre; }
  double py(double x_fwd, double /*y_left*/) const { return origin_y - x_fwd * pixels_per_metre; }
};

// Nearest-neighbour enlargement by an integer factor (keeps small frames' pixels crisp).
inline io::Image enlarge(const io::Image& in, std::int64_t factor) {
  if (factor <= 1) return in;
  io::Image out(in.height * factor, in.width * factor);
  for (std::int64_t y = 0; y < out.height; ++y)
    for (std::int64_t x = 0; x < out.width; ++x)
      for (int c = 0; c < 3; ++c) out.at(y, x, c) = in.at(y / factor, x / factor, c);
  return out;
}

// plan.png is at least this tall: smaller frames are enlarged by an integer factor first.
inline constexpr std::int64_t kPlanMinHeight = 256;

// Waypoint colour: green (first) to red (last).
inline Rgb waypoint_colour(std::int64_t i, std::int64_t n) {
  const double t = n > 1 ? double(i) / double(n - 1) : 0.0;
  return {static_cast<std::uint8_t>(40 + 215 * t), static_cast<std::uint8_t>(230 - 190 * t), 40};
}

// The polyline from the ego through waypoints (W, 3), in pixels.
inline std::vector<std::array<double, 2>> plan_points(const TopDownView& view, const Tensor<float>& waypoints) {
  std::vector<std::array<double, 2>> pts{{view.origin_x, view.origin_y}};
  for (std::int64_t i = 0; i < waypoints.size(0); ++i)
    pts.push_back({view.px(waypoints.at(i, 0), waypoints.at(i, 1)), view.py(waypoints.at(i, 0), waypoints.at(i, 1))});
  return pts;
}

inline void draw_polyline(io::Image& frame, const std::vector<std::array<double, 2>>& pts, double half_width, Rgb colour) {
  for (std::size_t i = 0; i + 1 < pts.size(); ++i)
    draw_segment(frame, pts[i][0], pts[i][1], pts[i + 1][0], pts[i + 1][1], half_width, colour);
}

// The frame (enlarged to at least kPlanMinHeight rows) with the planned waypoints (W, 3)
// (metres forward, metres left, degrees) drawn on it; with `hypotheses` (K, W, 3), the fan the
// plan was chosen from goes under it in thin light-blue lines (the view then fits them all).
inline io::Image draw_plan(const io::Image& last_frame, const Tensor<float>& waypoints, TopDownView* view_out = nullptr,
                           const Tensor<float>* hypotheses = nullptr) {
  io::Image frame = enlarge(last_frame, (kPlanMinHeight + last_frame.height - 1) / last_frame.height);
  const bool fan = hypotheses && hypotheses->size(0) > 1;
  const TopDownView view = TopDownView::fit(
      frame, fan ? hypotheses->reshape({hypotheses->size(0) * hypotheses->size(1), 3}) : waypoints);
  if (view_out) *view_out = view;
  const double r = std::max(1.0, std::round(double(frame.height) / 96.0));  // line half-width
  const Rgb outline{20, 20, 20}, path{255, 220, 40}, ego{255, 255, 255}, alternative{150, 200, 255};
  if (fan)  // each hypothesis a thin line ending in a disc, so a tight fan still shows at its far end
    for (std::int64_t k = 0; k < hypotheses->size(0); ++k) {
      const auto hp = plan_points(view, (*hypotheses)[k]);
      draw_polyline(frame, hp, r * 0.4, alternative);
      fill_disc(frame, hp.back()[0], hp.back()[1], r + 1, outline);
      fill_disc(frame, hp.back()[0], hp.back()[1], r, alternative);
    }
  const auto pts = plan_points(view, waypoints);
  const std::int64_t n = waypoints.size(0);
  draw_polyline(frame, pts, r + 1, outline);  // a dark outline first keeps the path visible on any ground
  draw_polyline(frame, pts, r * 0.5, path);
  for (std::int64_t i = 0; i < n; ++i) {
    fill_disc(frame, pts[i + 1][0], pts[i + 1][1], r + 1.5, outline);
    fill_disc(frame, pts[i + 1][0], pts[i + 1][1], r + 0.5, waypoint_colour(i, n));
  }
  fill_disc(frame, view.origin_x, view.origin_y, r + 2, outline);
  fill_disc(frame, view.origin_x, view.origin_y, r + 1, ego);
  return frame;
}

// ---- numbers: a 5x7 bitmap font of the digits and the minus sign ---------------------

// One row a byte, the 5 low bits from left (bit 4) to right (bit 0); top row first.
inline constexpr std::array<std::array<std::uint8_t, 7>, 11> kGlyphs = {{
    {0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E},  // 0
    {0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E},  // 1
    {0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F},  // 2
    {0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E},  // 3
    {0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02},  // 4
    {0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E},  // 5
    {0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E},  // 6
    {0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08},  // 7
    {0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E},  // 8
    {0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C},  // 9
    {0x00, 0x00, 0x00, 0x1F, 0x00, 0x00, 0x00},  // -
}};
inline constexpr int kGlyphW = 5, kGlyphH = 7;

inline const std::array<std::uint8_t, 7>& glyph(char c) { return kGlyphs[c == '-' ? 10 : c - '0']; }

// A clipping rectangle: what is drawn outside it is dropped.
struct Box {
  std::int64_t top = 0, left = 0, height = 0, width = 0;
  bool holds(std::int64_t y, std::int64_t x) const { return y >= top && y < top + height && x >= left && x < left + width; }
};

inline void fill_box(io::Image& img, const Box& b, const Box& clip, Rgb colour) {
  for (std::int64_t y = b.top; y < b.top + b.height; ++y)
    for (std::int64_t x = b.left; x < b.left + b.width; ++x)
      if (clip.holds(y, x) && y >= 0 && y < img.height && x >= 0 && x < img.width)
        for (int c = 0; c < 3; ++c) img.at(y, x, c) = colour[c];
}

// `number` in white digits `scale` pixels a font pixel, on a dark box whose top-left corner is
// (top, left), all within `clip`: legible on any image.
inline void draw_number(io::Image& img, std::int64_t number, std::int64_t top, std::int64_t left, int scale,
                        const Box& clip) {
  const std::string text = std::to_string(number);
  const std::int64_t pad = scale, advance = (kGlyphW + 1) * scale;
  const auto n = static_cast<std::int64_t>(text.size());
  fill_box(img, {top, left, kGlyphH * scale + 2 * pad, n * advance - scale + 2 * pad}, clip, Rgb{16, 16, 16});
  for (std::int64_t i = 0; i < n; ++i) {
    const auto& rows = glyph(text[static_cast<std::size_t>(i)]);
    for (int gy = 0; gy < kGlyphH; ++gy)
      for (int gx = 0; gx < kGlyphW; ++gx)
        if (rows[gy] >> (kGlyphW - 1 - gx) & 1)
          fill_box(img, {top + pad + gy * scale, left + pad + i * advance + gx * scale, scale, scale}, clip,
                   Rgb{255, 255, 255});
  }
}

// ---- contact sheet --------------------------------------------------------------------

struct SheetTile {
  io::Image image;
  bool is_input = false;  // input frames get a blue frame, generated ones an orange one
  // Drawn in the tile's top-left corner: generate numbers the inputs -F .. -1 (the last input is
  // -1) and the generated frames as their files (0 is frames/frame_0000.png).
  std::int64_t number = 0;
};

struct SheetLayout {
  std::int64_t columns = 1, rows = 1, tile_h = 0, tile_w = 0, gap = 4;
  std::int64_t height() const { return rows * tile_h + (rows + 1) * gap; }
  std::int64_t width() const { return columns * tile_w + (columns + 1) * gap; }

  // Up to `max_columns` per row; tiles wider than `max_tile_w` are shrunk (aspect kept).
  static SheetLayout of(std::int64_t count, std::int64_t frame_h, std::int64_t frame_w, std::int64_t max_columns = 5,
                        std::int64_t max_tile_w = 384) {
    SheetLayout l;
    l.columns = std::clamp<std::int64_t>(count, 1, max_columns);
    l.rows = (std::max<std::int64_t>(count, 1) + l.columns - 1) / l.columns;
    l.tile_w = std::min(frame_w, max_tile_w);
    l.tile_h = std::max<std::int64_t>(1, frame_h * l.tile_w / frame_w);
    return l;
  }
};

// Image pixels per font pixel of a tile's number: one per 64 rows of the tile, at least one.
inline int label_scale(std::int64_t tile_h) { return static_cast<int>(std::max<std::int64_t>(1, tile_h / 64)); }

inline io::Image contact_sheet(const std::vector<SheetTile>& tiles) {
  EPONA_CHECK(!tiles.empty(), "contact sheet: no frames");
  const auto& first = tiles.front().image;
  const SheetLayout l = SheetLayout::of(static_cast<std::int64_t>(tiles.size()), first.height, first.width);
  io::Image sheet(l.height(), l.width());
  std::fill(sheet.rgb.begin(), sheet.rgb.end(), std::uint8_t{32});
  const int border = static_cast<int>(std::max<std::int64_t>(1, l.tile_h / 64));
  for (std::size_t i = 0; i < tiles.size(); ++i) {
    const auto row = static_cast<std::int64_t>(i) / l.columns, col = static_cast<std::int64_t>(i) % l.columns;
    const std::int64_t top = l.gap + row * (l.tile_h + l.gap), left = l.gap + col * (l.tile_w + l.gap);
    const io::Image& src = tiles[i].image;
    const io::Image tile = (src.height == l.tile_h && src.width == l.tile_w) ? src : io::resize_bicubic(src, l.tile_h, l.tile_w);
    for (std::int64_t y = 0; y < l.tile_h; ++y)
      std::copy_n(tile.rgb.data() + y * l.tile_w * 3, l.tile_w * 3, &sheet.at(top + y, left, 0));
    draw_rect_outline(sheet, top, left, l.tile_h, l.tile_w, border,
                      tiles[i].is_input ? Rgb{60, 130, 255} : Rgb{255, 150, 30});
    draw_number(sheet, tiles[i].number, top + border, left + border, label_scale(l.tile_h),
                {top + border, left + border, l.tile_h - 2 * border, l.tile_w - 2 * border});
  }
  return sheet;
}

// Which of `count` generated frames go on the sheet: all when they fit in `slots`, else
// evenly spaced ones that include the first and the last.
inline std::vector<std::int64_t> sheet_picks(std::int64_t count, std::int64_t slots) {
  std::vector<std::int64_t> picks;
  if (count <= 0 || slots <= 0) return picks;
  if (count <= slots) {
    for (std::int64_t i = 0; i < count; ++i) picks.push_back(i);
    return picks;
  }
  for (std::int64_t k = 0; k < slots; ++k) {
    const std::int64_t i = slots == 1 ? count - 1 : k * (count - 1) / (slots - 1);
    if (picks.empty() || picks.back() != i) picks.push_back(i);
  }
  return picks;
}

}  // namespace epona::app
