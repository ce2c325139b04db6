// Tests of the contact sheet's numbered tiles (apps/epona/drawing.hpp): each tile's number is
// drawn in white on a dark box in its top-left corner, the glyphs are the font's (read back pixel
// by pixel), the rest of the tile is the frame, and a tile too small for its number clips it.
#include <doctest/doctest.h>

#include <cstdint>
#include <string>
#include <vector>

#include "../../apps/epona/drawing.hpp"

using namespace epona;
using app::Rgb;

namespace {

io::Image flat(std::int64_t h, std::int64_t w, std::uint8_t value) {
  io::Image img(h, w);
  std::fill(img.rgb.begin(), img.rgb.end(), value);
  return img;
}

bool is(const io::Image& img, std::int64_t y, std::int64_t x, Rgb c) {
  return img.at(y, x, 0) == c[0] && img.at(y, x, 1) == c[1] && img.at(y, x, 2) == c[2];
}

// Where tile `i` of the sheet starts.
std::pair<std::int64_t, std::int64_t> tile_origin(const app::SheetLayout& l, std::int64_t i) {
  return {l.gap + (i / l.columns) * (l.tile_h + l.gap), l.gap + (i % l.columns) * (l.tile_w + l.gap)};
}

}  // namespace

TEST_CASE("each tile carries its number in its top-left corner, white on a dark box") {
  const std::vector<app::SheetTile> tiles = {{flat(64, 128, 128), true, -2},
                                             {flat(64, 128, 128), true, -1},
                                             {flat(64, 128, 128), false, 0},
                                             {flat(64, 128, 128), false, 17}};
  const io::Image sheet = app::contact_sheet(tiles);
  const auto l = app::SheetLayout::of(4, 64, 128);
  const int border = 1, scale = app::label_scale(l.tile_h);  // 64-row tiles: 1-pixel borders, 1-pixel font
  REQUIRE(scale == 1);
  for (std::int64_t i = 0; i < 4; ++i) {
    INFO("tile " << i);
    const auto [top, left] = tile_origin(l, i);
    const std::string text = std::to_string(tiles[std::size_t(i)].number);
    const std::int64_t y0 = top + border + 1, x0 = left + border + 1;  // inside the box's 1-pixel margin
    // Every font pixel of every glyph, white where the glyph is set, the dark box elsewhere.
    std::int64_t white = 0;
    for (std::size_t k = 0; k < text.size(); ++k)
      for (int gy = 0; gy < app::kGlyphH; ++gy)
        for (int gx = 0; gx < app::kGlyphW; ++gx) {
          const bool set = app::glyph(text[k])[gy] >> (app::kGlyphW - 1 - gx) & 1;
          const std::int64_t y = y0 + gy, x = x0 + std::int64_t(k) * (app::kGlyphW + 1) + gx;
          CHECK(is(sheet, y, x, set ? Rgb{255, 255, 255} : Rgb{16, 16, 16}));
          white += set;
        }
    CHECK(white > 0);
    CHECK(is(sheet, top + border, left + border, Rgb{16, 16, 16}));  // the box's corner
    // Past the box, the frame itself.
    const std::int64_t box_w = std::int64_t(text.size()) * (app::kGlyphW + 1) + 1;
    CHECK(is(sheet, top + 20, left + border + box_w + 1, Rgb{128, 128, 128}));
    CHECK(is(sheet, top + l.tile_h / 2, left + l.tile_w / 2, Rgb{128, 128, 128}));
  }
}

TEST_CASE("the font draws the digits and the minus sign distinctly; big tiles get bigger digits") {
  for (char a : std::string("0123456789-"))
    for (char b : std::string("0123456789-"))
      if (a != b) CHECK_MESSAGE(app::glyph(a) != app::glyph(b), a << " and " << b);
  CHECK(app::label_scale(64) == 1);
  CHECK(app::label_scale(192) == 3);
  io::Image img = flat(40, 40, 100);
  app::draw_number(img, 8, 0, 0, 3, {0, 0, 40, 40});
  // '8' at 3 pixels a font pixel: its top-left font pixel (row 0, column 1) covers 3x3 pixels.
  for (std::int64_t y = 3; y < 6; ++y)
    for (std::int64_t x = 6; x < 9; ++x) CHECK(is(img, y, x, Rgb{255, 255, 255}));
  CHECK(is(img, 3, 3, Rgb{16, 16, 16}));  // row 0, column 0 of '8' is clear
}

TEST_CASE("a tile too small for its number clips it to the tile") {
  io::Image img = flat(6, 6, 100);
  app::draw_number(img, -123, 0, 0, 1, {1, 1, 4, 4});
  for (std::int64_t y = 0; y < 6; ++y)
    for (std::int64_t x = 0; x < 6; ++x) {
      const bool inside = y >= 1 && y < 5 && x >= 1 && x < 5;
      if (!inside) CHECK(is(img, y, x, Rgb{100, 100, 100}));
    }
}

#include "epona/io/stb_implementation.hpp"
