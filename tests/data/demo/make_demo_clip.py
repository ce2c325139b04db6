#!/usr/bin/env python3
"""Renders the bundled demo clip: a few 64x128 frames of a straight two-lane road seen from a car
driving forward at 2 m per frame (36 km/h at Epona's 5 Hz), plus poses.csv with the motion into
each frame. Pure Python (no numpy/PIL), deterministic: the frames are rendered at 4x4 supersampling
with a pinhole camera 1.6 m above the road and box-filtered down.

    python3 tests/data/demo/make_demo_clip.py [out_dir] [frames]
"""
import math
import os
import struct
import sys
import zlib

H, W, SS = 64, 128, 4                  # output size, supersampling factor
RH, RW = H * SS, W * SS                # render size
FOCAL = 0.72 * RW                      # pixels (about 70 degrees horizontal field of view)
CAM_HEIGHT = 1.6                       # metres
HORIZON = 0.42 * RH                    # row of the horizon
STEP = 2.0                             # metres forward per frame
SKY_TOP, SKY_LOW = (96, 146, 206), (196, 212, 228)
HAZE = (186, 200, 214)


def hash01(*ints):
    """A repeatable pseudo-random number in [0, 1) from integers."""
    h = 2166136261
    for i in ints:
        h = ((h ^ (i & 0xFFFFFFFF)) * 16777619) & 0xFFFFFFFF
        h ^= h >> 13
    return (h & 0xFFFF) / 65536.0


def mix(a, b, t):
    return tuple(x + (y - x) * t for x, y in zip(a, b))


def ground_colour(s, x):
    """Road surface at distance s along the road and x metres to the right of the ego lane centre."""
    noise = hash01(int(math.floor(s * 3)), int(math.floor(x * 3))) - 0.5
    if -5.4 <= x <= 1.8:  # two lanes: ours (x in [-1.8, 1.8]) and the oncoming one
        line = (abs(x - 1.72) < 0.09 or abs(x + 5.32) < 0.09 or
                (abs(x + 1.8) < 0.07 and (s % 9.0) < 3.0))
        if line:
            return (228, 228, 220)
        g = 92 + 14 * noise
        return (g, g, g + 4)
    if -6.4 <= x <= 2.8:  # gravel shoulder
        return (150 + 20 * noise, 140 + 20 * noise, 118 + 16 * noise)
    stripe = 8 * math.sin(s * 0.9 + x * 0.3)
    return (64 + 24 * noise, 116 + 26 * noise + stripe, 46 + 14 * noise)


def render_ground(ego_s):
    img = [[None] * RW for _ in range(RH)]
    cx = RW / 2.0
    for v in range(RH):
        vc = v + 0.5
        if vc <= HORIZON + 0.5:
            t = max(0.0, vc / HORIZON)
            row = mix(SKY_TOP, SKY_LOW, t ** 1.4)
            img[v] = [row] * RW
            continue
        z = FOCAL * CAM_HEIGHT / (vc - HORIZON)
        fog = 1.0 - math.exp(-z / 140.0)
        line = img[v]
        for u in range(RW):
            x = (u + 0.5 - cx) * z / FOCAL
            line[u] = mix(ground_colour(z + ego_s, x), HAZE, fog)
    return img


def project(x, y_up, z):
    return RW / 2.0 + FOCAL * x / z, HORIZON + FOCAL * (CAM_HEIGHT - y_up) / z


def fill_box(img, u0, v0, u1, v1, colour, z):
    fog = 1.0 - math.exp(-z / 140.0)
    c = mix(colour, HAZE, fog)
    for v in range(max(0, int(v0)), min(RH, int(math.ceil(v1)))):
        for u in range(max(0, int(u0)), min(RW, int(math.ceil(u1)))):
            img[v][u] = c


def fill_ellipse(img, cu, cv, ru, rv, colour, z, shade_seed):
    fog = 1.0 - math.exp(-z / 140.0)
    for v in range(max(0, int(cv - rv)), min(RH, int(cv + rv) + 1)):
        for u in range(max(0, int(cu - ru)), min(RW, int(cu + ru) + 1)):
            du, dv = (u + 0.5 - cu) / ru, (v + 0.5 - cv) / rv
            if du * du + dv * dv <= 1.0:
                n = hash01(shade_seed, u // 3, v // 3) - 0.5
                light = 1.0 - 0.25 * dv + 0.3 * n
                img[v][u] = mix(tuple(ch * light for ch in colour), HAZE, fog)


def draw_trees(img, ego_s):
    trees = []
    for k in range(-2, 30):
        for side, base_x in ((1, 9.0), (-1, -12.5)):
            s = k * 11.0 + (0.0 if side > 0 else 5.5) + 3.0 * hash01(k, side)
            z = s - ego_s
            if 3.0 < z < 170.0:
                trees.append((z, base_x + side * 3.0 * hash01(k, side, 7), k * 2 + (side > 0)))
    for z, x, seed in sorted(trees, reverse=True):  # far to near
        height = 5.0 + 3.0 * hash01(seed, 3)
        u0, v_ground = project(x - 0.2, 0.0, z)
        u1, v_top = project(x + 0.2, height * 0.55, z)
        fill_box(img, u0, v_top, u1, v_ground, (88, 62, 40), z)
        cu, cv = project(x, height * 0.7, z)
        r = FOCAL * (1.6 + 0.8 * hash01(seed, 5)) / z
        fill_ellipse(img, cu, cv, r, r * 1.25, (44, 92, 40), z, seed)


def draw_lead_car(img, frame):
    z = 17.0 - 0.6 * frame  # slowly closing in
    u0, v_ground = project(-0.9, 0.0, z)
    u1, v_top = project(0.9, 1.5, z)
    fill_box(img, u0, v_top, u1, v_ground, (150, 28, 30), z)                      # body
    _, v_win0 = project(0.0, 1.45, z)
    _, v_win1 = project(0.0, 1.0, z)
    wu0, _ = project(-0.75, 0.0, z)
    wu1, _ = project(0.75, 0.0, z)
    fill_box(img, wu0, v_win0, wu1, v_win1, (40, 46, 56), z)                        # rear window
    _, v_l0 = project(0.0, 0.9, z)
    _, v_l1 = project(0.0, 0.75, z)
    for lx in (-0.85, 0.55):
        lu0, _ = project(lx, 0.0, z)
        lu1, _ = project(lx + 0.3, 0.0, z)
        fill_box(img, lu0, v_l0, lu1, v_l1, (250, 70, 50), z)                       # tail lights
    _, v_sh = project(0.0, -0.05, z)
    fill_box(img, u0 - 2, v_ground, u1 + 2, v_sh + 2, (30, 30, 32), z)              # shadow


def downsample(img):
    out = bytearray()
    for y in range(H):
        out.append(0)  # PNG filter type 0 for this row
        for x in range(W):
            acc = [0.0, 0.0, 0.0]
            for v in range(y * SS, y * SS + SS):
                row = img[v]
                for u in range(x * SS, x * SS + SS):
                    p = row[u]
                    acc[0] += p[0]
                    acc[1] += p[1]
                    acc[2] += p[2]
            out.extend(max(0, min(255, int(a / (SS * SS) + 0.5))) for a in acc)
    return bytes(out)


def write_png(path, raw_rows):
    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)

    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", W, H, 8, 2, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw_rows, 9)) + chunk(b"IEND", b"")
    with open(path, "wb") as f:
        f.write(png)


def main():
    out_dir = sys.argv[1] if len(sys.argv) > 1 else os.path.dirname(os.path.abspath(__file__))
    frames = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    os.makedirs(out_dir, exist_ok=True)
    for i in range(frames):
        ego_s = STEP * i
        img = render_ground(ego_s)
        draw_trees(img, ego_s)
        draw_lead_car(img, i)
        write_png(os.path.join(out_dir, "frame_%02d.png" % i), downsample(img))
    with open(os.path.join(out_dir, "poses.csv"), "w") as f:
        f.write("# motion into each frame (ego frame of the previous one): x m forward, y m left, yaw deg left\n")
        f.write("x,y,yaw\n")
        for _ in range(frames):
            f.write("%.1f,0.0,0.0\n" % STEP)


if __name__ == "__main__":
    main()
