// epona/synth/scenery.hpp — what stands beside the road: trees (trunk + crown), poles (street
// lights, signs) and buildings (boxes of varied size and colour), placed along each side by a
// random walk in arc length. An object is kept only if it stands clear of the road everywhere
// nearby (on a tight curve a point beside one stretch can lie on another).
#pragma once

#include <algorithm>
#include <cmath>
#include <vector>

#include "epona/synth/geometry.hpp"
#include "epona/synth/rng.hpp"
#include "epona/synth/road.hpp"

namespace epona::synth {

enum class PropKind { Tree, Pole, Building };

struct Prop {
  PropKind kind = PropKind::Tree;
  double s = 0;          // arc length it stands at (for culling)
  Pose2 pose;            // footprint centre, yaw along the road
  double length = 1, width = 1, height = 1;  // footprint along x, y of pose; height
  double crown = 0;      // trees: crown radius; poles: arm length
  Rgb colour, colour2;   // trunk/crown, wall/roof, pole
};

// How built-up a drive's surroundings are (per side, objects per 100 m).
struct SceneryStyle {
  double trees = 6, poles = 2, buildings = 1.5;
  double setback = 4;  // m from the kerb to the nearest object
};

inline std::vector<Prop> place_scenery(Rng& rng, const Road& road, const RoadLayout& layout, const SceneryStyle& style,
                                       double s0, double s1) {
  std::vector<Prop> props;
  const double total = style.trees + style.poles + style.buildings;
  if (total <= 0) return props;
  for (int side = -1; side <= 1; side += 2) {
    Rng r = rng.split();
    const double edge = side < 0 ? layout.right_edge() - layout.kerb : layout.left_edge() + layout.kerb;
    for (double s = s0 + r.uniform(0, 10); s < s1; s += r.uniform(0.3, 1.7) * 100.0 / total) {
      const double pick = r.uniform(0, total);
      Prop p;
      p.s = s;
      double offset;  // from the kerb to the footprint centre
      if (pick < style.trees) {
        p.kind = PropKind::Tree;
        p.height = r.uniform(5, 12);
        p.crown = r.uniform(1.5, 3.2);
        p.length = p.width = r.uniform(0.25, 0.45);  // trunk
        offset = style.setback + p.crown + r.uniform(0, 14);
        p.colour = {0.33f, 0.24f, 0.16f};
        const double g = r.uniform(0.75, 1.15);
        p.colour2 = scaled(Rgb{0.17f + float(r.uniform(0, 0.1)), 0.36f, 0.12f}, g);
      } else if (pick < style.trees + style.poles) {
        p.kind = PropKind::Pole;
        p.height = r.uniform(6, 9);
        p.length = p.width = 0.22;
        p.crown = r.chance(0.7) ? r.uniform(1.2, 2.2) : 0.0;  // lamp arm over the road
        offset = r.uniform(0.6, 1.4);
        p.colour = scaled(Rgb{0.55f, 0.56f, 0.58f}, r.uniform(0.7, 1.2));
      } else {
        p.kind = PropKind::Building;
        p.length = r.uniform(10, 35), p.width = r.uniform(8, 22), p.height = r.uniform(5, 28);
        offset = style.setback + 0.5 * p.width + r.uniform(2, 15);
        static const Rgb walls[] = {{0.78f, 0.72f, 0.6f}, {0.62f, 0.62f, 0.63f}, {0.6f, 0.34f, 0.26f}, {0.86f, 0.85f, 0.82f},
                                    {0.45f, 0.5f, 0.58f}, {0.7f, 0.6f, 0.45f}, {0.35f, 0.36f, 0.38f}, {0.8f, 0.78f, 0.7f}};
        p.colour = scaled(walls[r.below(8)], r.uniform(0.85, 1.1));
        p.colour2 = scaled(Rgb{0.3f, 0.28f, 0.27f}, r.uniform(0.7, 1.3));
      }
      const double d = edge + side * offset;
      p.pose = road.at(s, d);
      const double radius = 0.5 * std::hypot(p.length, p.width) + (p.kind == PropKind::Tree ? p.crown : 0.0);
      const double clear = side < 0 ? -layout.right_edge() + layout.kerb : layout.left_edge() + layout.kerb;
      if (road.distance_to(p.pose.x, p.pose.y, s - 200, s + 200) < clear + radius + 0.5 - (p.kind == PropKind::Pole ? 0.6 : 0.0))
        continue;
      props.push_back(p);
    }
  }
  std::stable_sort(props.begin(), props.end(), [](const Prop& a, const Prop& b) { return a.s < b.s; });
  return props;
}

}  // namespace epona::synth
