// Tests for epona/cpu/pixel_shuffle.hpp and epona/nn/pixel_shuffle.hpp against float64 loops
// written from the spec's index formulas (§3.4-§3.6): unshuffle/shuffle channel order, exact
// inverses, the averaging and duplicating shortcuts at every (C_in, C_out, r) pattern f32c32
// uses (scaled down), their closed forms (2x2 average pool, nearest 2x upsample, 32-channel
// mean / repeat), accumulation into a residual, and the errors for sizes that do not divide.
// Data movement is exact; averaging of g values in float32: rel <= 1e-6.
#include <doctest/doctest.h>

#include "dcae_reference.hpp"
#include "epona/cpu/context.hpp"
#include "epona/nn/pixel_shuffle.hpp"

using namespace epona;
using dcae_ref::HostTensor;
using dcae_ref::i64;

TEST_CASE("pixel_unshuffle / pixel_shuffle follow torch's channel order and invert each other") {
  cpu::Context ctx;
  for (i64 r : {2, 3}) {
    const i64 N = 2, C = 3, H = 4 * r, W = 5 * r;
    const HostTensor x = dcae_ref::random_tensor({N, C, H, W}, 10 + r);
    const HostTensor u = nn::pixel_unshuffle(ctx, x, r);
    CHECK(u.shape() == Shape{N, C * r * r, H / r, W / r});
    CHECK(dcae_ref::rel_max(u, dcae_ref::unshuffle(dcae_ref::to_vec(x), N, C, H, W, r)) == 0);
    const HostTensor back = nn::pixel_shuffle(ctx, u, r);
    CHECK(dcae_ref::rel_max(back, dcae_ref::to_vec(x)) == 0);
    const HostTensor s = nn::pixel_shuffle(ctx, x, 1);  // r = 1 is a copy
    CHECK(dcae_ref::rel_max(s, dcae_ref::to_vec(x)) == 0);
    const HostTensor y = dcae_ref::random_tensor({N, C * r * r, 3, 2}, 20 + r);
    CHECK(dcae_ref::rel_max(nn::pixel_shuffle(ctx, y, r), dcae_ref::shuffle(dcae_ref::to_vec(y), N, C * r * r, 3, 2, r)) ==
          0);
  }
}

TEST_CASE("channel averaging shortcut at the f32c32 patterns") {
  cpu::Context ctx;
  struct P { i64 C, Co, r; };
  // 256->512 r2 (g=2), 512->512 r2 (g=4), 1024->32 r1 (g=32), scaled; plus an odd g = 3.
  for (const P& p : {P{4, 8, 2}, P{8, 8, 2}, P{64, 2, 1}, P{3, 4, 2}}) {
    INFO("C=" << p.C << " Co=" << p.Co << " r=" << p.r);
    const i64 N = 2, H = 6, W = 10;
    const HostTensor x = dcae_ref::random_tensor({N, p.C, H, W}, 30);
    const HostTensor y = nn::channel_average_down(ctx, x, p.Co, p.r);
    CHECK(y.shape() == Shape{N, p.Co, H / p.r, W / p.r});
    CHECK(dcae_ref::rel_max(y, dcae_ref::average_shortcut(dcae_ref::to_vec(x), N, p.C, H, W, p.r, p.Co)) <= 1e-6);
  }
  // Closed form of g = 4 at r = 2 with C_out = C: a 2x2 average pool of each channel.
  const HostTensor x = dcae_ref::random_tensor({1, 3, 4, 6}, 31);
  const HostTensor pool = nn::channel_average_down(ctx, x, 3, 2);
  for (i64 c = 0; c < 3; ++c)
    for (i64 y = 0; y < 2; ++y)
      for (i64 xx = 0; xx < 3; ++xx) {
        const double mean = (double(x.at(0, c, 2 * y, 2 * xx)) + x.at(0, c, 2 * y, 2 * xx + 1) +
                             x.at(0, c, 2 * y + 1, 2 * xx) + x.at(0, c, 2 * y + 1, 2 * xx + 1)) / 4;
        CHECK(pool.at(0, c, y, xx) == doctest::Approx(mean).epsilon(1e-6));
      }
}

TEST_CASE("channel duplicating shortcut at the f32c32 patterns") {
  cpu::Context ctx;
  struct P { i64 C, Co, r; };
  // 32->1024 r1 (rep 32), 1024->1024 r2 (rep 4), 1024->512 r2 (rep 2), scaled.
  for (const P& p : {P{2, 64, 1}, P{8, 8, 2}, P{8, 4, 2}, P{3, 3, 3}}) {
    INFO("C=" << p.C << " Co=" << p.Co << " r=" << p.r);
    const i64 N = 2, H = 3, W = 5;
    const HostTensor x = dcae_ref::random_tensor({N, p.C, H, W}, 40);
    const HostTensor y = nn::channel_duplicate_up(ctx, x, p.Co, p.r);
    CHECK(y.shape() == Shape{N, p.Co, H * p.r, W * p.r});
    CHECK(dcae_ref::rel_max(y, dcae_ref::duplicate_shortcut(dcae_ref::to_vec(x), N, p.C, H, W, p.r, p.Co)) == 0);
  }
  // Closed forms: rep 4 = nearest-neighbour 2x; rep 2: out[c](2y+i, 2x+j) = x[2c+i](y, x).
  const HostTensor x = dcae_ref::random_tensor({1, 4, 2, 3}, 41);
  const HostTensor nearest = nn::channel_duplicate_up(ctx, x, 4, 2), halves = nn::channel_duplicate_up(ctx, x, 2, 2);
  for (i64 c = 0; c < 4; ++c)
    for (i64 y = 0; y < 4; ++y)
      for (i64 xx = 0; xx < 6; ++xx) {
        CHECK(nearest.at(0, c, y, xx) == x.at(0, c, y / 2, xx / 2));
        if (c < 2) CHECK(halves.at(0, c, y, xx) == x.at(0, 2 * c + y % 2, y / 2, xx / 2));
      }
}

TEST_CASE("shortcuts accumulate into a residual sum") {
  cpu::Context ctx;
  const HostTensor x = dcae_ref::random_tensor({1, 4, 4, 4}, 50);
  HostTensor down = dcae_ref::random_tensor({1, 8, 2, 2}, 51);
  const HostTensor base = down.clone(), avg = nn::channel_average_down(ctx, x, 8, 2);
  nn::add_channel_average_down(ctx, x, down, 2);
  for (i64 i = 0; i < down.numel(); ++i) CHECK(down.data()[i] == base.data()[i] + avg.data()[i]);
  HostTensor up = dcae_ref::random_tensor({1, 2, 8, 8}, 52);
  const HostTensor base_up = up.clone(), dup = nn::channel_duplicate_up(ctx, x, 2, 2);
  nn::add_channel_duplicate_up(ctx, x, up, 2);
  for (i64 i = 0; i < up.numel(); ++i) CHECK(up.data()[i] == base_up.data()[i] + dup.data()[i]);
}

TEST_CASE("shuffles refuse sizes and channel counts that do not divide") {
  cpu::Context ctx;
  CHECK_THROWS_WITH_AS(nn::pixel_unshuffle(ctx, dcae_ref::random_tensor({1, 2, 5, 4}, 1), 2),
                       doctest::Contains("not divisible by factor 2"), Error);
  CHECK_THROWS_WITH_AS(nn::pixel_shuffle(ctx, dcae_ref::random_tensor({1, 6, 2, 2}, 1), 2),
                       doctest::Contains("not divisible by factor"), Error);
  CHECK_THROWS_WITH_AS(nn::channel_average_down(ctx, dcae_ref::random_tensor({1, 3, 4, 4}, 1), 5, 2),
                       doctest::Contains("do not split into 5 groups"), Error);
  CHECK_THROWS_WITH_AS(nn::channel_duplicate_up(ctx, dcae_ref::random_tensor({1, 3, 4, 4}, 1), 5, 1),
                       doctest::Contains("not a multiple of the 3 input channels"), Error);
  CHECK_THROWS_WITH_AS(nn::pixel_unshuffle(ctx, dcae_ref::random_tensor({2, 4, 4}, 1), 2),
                       doctest::Contains("(N, C, H, W)"), Error);
}
