#!/usr/bin/env python3
"""Writes the seed corpora fuzz/corpus/<target>/ (small, valid or nearly valid inputs that show
the fuzzer each format's structure). Deterministic, standard library only; the test fixtures it
reads are in tests/data. Run from anywhere: python3 fuzz/make_corpus.py
The JPEG seeds fuzz/corpus/image/*.jpg.in are not written here: they are baseline JPEGs from
stb_image_write's stbi_write_jpg (after the option byte, see fuzz_image.cpp), kept as files."""
import json
import pathlib
import shutil
import struct
import zipfile
import zlib

ROOT = pathlib.Path(__file__).resolve().parent.parent
DATA = ROOT / "tests" / "data"
OUT = ROOT / "fuzz" / "corpus"
RECORD_SEP = b"\xff\xfeREC"  # fuzz_torch_checkpoint.cpp
YAW_SEP = b"\xff\xfeYAW"     # fuzz_poses_npy.cpp


def put(target, name, data):
    d = OUT / target
    d.mkdir(parents=True, exist_ok=True)
    (d / name).write_bytes(data if isinstance(data, bytes) else data.encode())


# ---- safetensors -------------------------------------------------------------------------
def safetensors(tensors, metadata=None):
    header, blob = {}, b""
    if metadata is not None:
        header["__metadata__"] = metadata
    for name, (dtype, shape, data) in tensors.items():
        header[name] = {"dtype": dtype, "shape": shape, "data_offsets": [len(blob), len(blob) + len(data)]}
        blob += data
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    return struct.pack("<Q", len(text)) + text + blob


def f32(*v):
    return struct.pack("<%df" % len(v), *v)


put("safetensors", "f32_bf16_meta.safetensors", safetensors(
    {"w": ("F32", [2, 3], f32(1, -2, 3.5, 0, -0.0, 1e-3)), "b": ("BF16", [3], b"\x80\x3f\x00\x40\xc0\x7f")},
    {"format": "pt", "note": "seed"}))
put("safetensors", "f16_i64_empty_scalar.safetensors", safetensors(
    {"h": ("F16", [2, 2], struct.pack("<4e", 1, -1, 0.5, 65504)), "ids": ("I64", [2], struct.pack("<2q", -1, 7)),
     "empty": ("F32", [0, 3], b""), "s": ("F32", [], f32(0.25))}))
put("safetensors", "no_tensors.safetensors", safetensors({}, {"a": "b"}))
put("safetensors", "special_values.safetensors", safetensors(
    {"x": ("F32", [4], struct.pack("<4I", 0x7f800000, 0xff800000, 0x7fc00000, 1))}))

# ---- ZIP / pickle / torch checkpoints from the torch.save fixtures ----------------------
PKL = ["fp32_plain", "bf16_world", "fp16_dcae", "views", "noncontiguous", "ordered_state_dict", "no_state_dict",
       "hostile_os_system", "zip64_full", "zip64_local"]
for name in PKL:
    raw = (DATA / "pkl" / f"{name}.pkl").read_bytes()
    put("zip", f"{name}.zip", raw)
    with zipfile.ZipFile(DATA / "pkl" / f"{name}.pkl") as z:
        files = {i.filename.split("/", 1)[1]: z.read(i) for i in z.infolist()}
    put("pickle", f"{name}.pkl", files["data.pkl"])
    records = sorted((int(k[5:]), v) for k, v in files.items() if k.startswith("data/"))
    assert [i for i, _ in records] == list(range(len(records))), name
    put("torch_checkpoint", f"{name}.bin", RECORD_SEP.join([files["data.pkl"]] + [v for _, v in records]))

# ---- configs ----------------------------------------------------------------------------
golden = json.loads((DATA / "golden" / "configs.json").read_text())
put("config_json", "golden.json", json.dumps(golden, indent=1))
put("config_json", "plain_world.json", json.dumps(golden["world_model_config"]))
put("config_json", "golden_compact.json",
    json.dumps({"world_model_config": golden["world_model_config"], "dcae": golden["dcae"]}, separators=(",", ":")))


# ---- .npy -------------------------------------------------------------------------------
def npy(descr, shape, data, version=1):
    sh = "(" + ", ".join(map(str, shape)) + ("," if len(shape) == 1 else "") + ")"
    header = "{'descr': '%s', 'fortran_order': False, 'shape': %s, }" % (descr, sh)
    pre = 10 if version == 1 else 12
    header += " " * (-(pre + len(header) + 1) % 64) + "\n"
    length = struct.pack("<H", len(header)) if version == 1 else struct.pack("<I", len(header))
    return b"\x93NUMPY" + bytes([version, 0]) + length + header.encode() + data


for f in sorted((DATA / "poses" / "npy").glob("*.npy")):
    put("npy", f.name, f.read_bytes())
put("npy", "f8_3d_v2.npy", npy("<f8", [2, 1, 2], struct.pack("<4d", 1.5, -2, 1e300, 0), 2))
put("npy", "f2_empty_v3.npy", npy("<f2", [0], b"", 3))


def absolute(poses):  # 4x4 row-major ego-to-world, yaw in degrees around z
    import math
    out = []
    for x, y, yaw in poses:
        c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
        out += [c, -s, 0, x, s, c, 0, y, 0, 0, 1, 0, 0, 0, 0, 1]
    return out


ABS = absolute([(0, 0, 0), (1.2, 0.1, 2), (2.5, 0.3, 5)])
for f in sorted((DATA / "poses").glob("absolute_*.npy")):
    put("poses_npy", f.name, f.read_bytes())
put("poses_npy", "absolute_n44_small.npy", npy("<f8", [3, 4, 4], struct.pack("<48d", *ABS)))
put("poses_npy", "rows_n3.npy", npy("<f4", [3, 3], f32(0.5, 0, 1, 0.6, 0.01, -1, 0.7, 0, 0)))
put("poses_npy", "planned_sw3.npy", npy("<f4", [2, 2, 3], f32(*range(12))))
for d in ["demo_n2_f4", "demo_1n2_f8", "demo_mismatch"]:
    put("poses_npy", f"{d}.pair", (DATA / "poses" / d / "pose.npy").read_bytes() + YAW_SEP +
        (DATA / "poses" / d / "yaw.npy").read_bytes())

# ---- pose CSV / JSON ---------------------------------------------------------------------
put("poses_csv", "header.csv", "x,y,yaw\n0.5,0.01,0.2\n0.6,-0.02,-1.5\n")
put("poses_csv", "reordered.csv", "\ufeff# recorded at 5 Hz\nyaw, x, y\n1.0, 0.5, 0\n-2e-1, +0.4, 1e-3  # turn\n")
put("poses_csv", "whitespace.txt", "0.5 0 0\n\t0.6\t0.1\t-3\n\n0.7 0 1.25\n")
put("poses_json", "list.json", json.dumps([[0.5, 0.0, 0.2], [0.6, -0.02, -1.5]]))
put("poses_json", "objects.json", json.dumps([{"x": 0.5, "y": 0, "yaw": 1}, {"yaw": -1, "x": 0.4, "y": 1e-3}]))
put("poses_json", "poses.json", json.dumps({"poses": [[1, 2, 3]]}))
put("poses_json", "absolute.json",
    json.dumps({"absolute": [[ABS[16 * i + 4 * r:16 * i + 4 * r + 4] for r in range(4)] for i in range(3)]}))

# ---- planned trajectories ----------------------------------------------------------------
traj = [[[0.5 * (w + 1), 0.01 * w, 0.1 * w - s] for w in range(3)] for s in range(2)]
rows = "".join(f"{s},{w},{x},{y},{yaw}\n" for s, step in enumerate(traj) for w, (x, y, yaw) in enumerate(step))
put("trajectory_csv", "two_steps.csv", "# epona planned trajectory\nstep,waypoint,x,y,yaw\n" + rows)
put("trajectory_csv", "one_waypoint.csv", "step,waypoint,x,y,yaw\n0,0,-0.0,1e-45,3.4028235e38\n")
put("trajectory_json", "two_steps.json", json.dumps(
    {"format": "epona-trajectory", "units": {"x": "m, forward", "y": "m, left", "yaw": "deg, left turn positive"},
     "steps": traj}))
put("trajectory_json", "bare.json", json.dumps({"steps": [[[1, 2, 3]]]}))


# ---- PNG images (the first byte is fuzz_image.cpp's option byte) -------------------------
def png(width, height, color_type, depth, interlace=False, palette=None):
    channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}[color_type]
    bpp = max(1, channels * depth // 8)

    def sample(x, y):
        return bytes(((x * 29 + y * 53 + c * 101) % 256) for c in range(bpp))

    def scanlines(xs, ys):  # filter type cycles through 0-4 so every PNG filter is exercised
        xs = list(xs)
        if depth < 8:  # packed samples: the row is ceil(width * depth / 8) bytes
            return b"".join(bytes([y % 5]) + bytes((x * 29 + y * 53) % 256 for x in range((len(xs) * depth + 7) // 8))
                            for y in ys)
        return b"".join(bytes([y % 5]) + b"".join(sample(x, y) for x in xs) for y in ys)

    if interlace:  # Adam7: seven passes of a sub-grid each
        passes = [(0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2)]
        raw = b"".join(scanlines(range(x0, width, dx), range(y0, height, dy))
                       for x0, y0, dx, dy in passes if x0 < width and y0 < height)
    else:
        raw = scanlines(range(width), range(height))

    def chunk(kind, body):
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", width, height, depth, color_type, 0, 0, 1 if interlace else 0)
    out = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
    if palette:
        out += chunk(b"PLTE", palette)
    return out + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b"")


EXACT, CONVERT, RESIZE, CROP, COVER, TARGET, WIDE = 0, 1, 2, 4, 6, 8, 16
put("image", "rgb8_32x32.png.in", bytes([EXACT]) + png(32, 32, 2, 8))
put("image", "rgb8_40x24_resize.png.in", bytes([RESIZE | TARGET]) + png(40, 24, 2, 8))
put("image", "rgb8_72x40_cover_wide.png.in", bytes([COVER | TARGET | WIDE]) + png(72, 40, 2, 8))
put("image", "rgb8_36x33_crop.png.in", bytes([CROP | TARGET]) + png(36, 33, 2, 8))
put("image", "rgb8_9x7_adam7.png.in", bytes([CONVERT]) + png(9, 7, 2, 8, interlace=True))
put("image", "gray8_4x4.png.in", bytes([CONVERT | RESIZE | TARGET]) + png(4, 4, 0, 8))
put("image", "gray1_8x3.png.in", bytes([CONVERT]) + png(8, 3, 0, 1))
put("image", "gray_alpha16_2x2.png.in", bytes([CONVERT | COVER | TARGET | WIDE]) + png(2, 2, 4, 16))
put("image", "rgba8_4x4.png.in", bytes([CONVERT | RESIZE | TARGET]) + png(4, 4, 6, 8))
put("image", "rgb16_2x2.png.in", bytes([EXACT]) + png(2, 2, 2, 16))
put("image", "palette4_4x4.png.in", bytes([CONVERT]) + png(4, 4, 3, 4, palette=bytes(range(48))))

# ---- issue #36: the red team's classes, small enough for libFuzzer's default lengths -------
DEEP = 3000  # far past the 64-level JSON limit; the targets must refuse, not recurse
put("config_json", "deep_open.json", "[" * DEEP)
put("config_json", "deep_under_key.json", '{"world_model_config": ' + "[" * DEEP + "]" * DEEP + "}")
put("config_json", "duplicate_key.json", '{"world_model_config": {"n_embd": 1, "n_embd": 2}}')
put("config_json", "long_string.json", '{"world_model_config": {"n_embd": "' + "\u001b" * 2000 + '"}}')
put("poses_json", "deep_poses.json", '{"poses": ' + "[" * DEEP)
put("poses_json", "deep_absolute.json", '{"absolute": ' + "[" * DEEP + "]" * DEEP + "}")
put("poses_json", "duplicate_key.json", '[{"x": 1, "y": 2, "yaw": 3, "x": 4}]')
put("poses_json", "deep_value.json", "[[1, 2, " + "[" * 60 + "]" * 60 + "]]")
put("trajectory_json", "deep_steps.json", '{"steps": ' + "[" * DEEP + "]" * DEEP + "}")
put("trajectory_json", "duplicate_steps.json", '{"steps": [[[1, 2, 3]]], "steps": [[[4, 5, 6]]]}')
put("poses_csv", "commas.csv", "," * 5000 + "\n")
put("poses_csv", "control_bytes.csv", "x,y,yaw\n1,2,\x1b[2J\x00\n")
put("trajectory_csv", "commas.csv", "step,waypoint,x,y,yaw\n" + "," * 5000 + "\n")
many = {f"layer.{i}.weight": ("F32", [1], f32(float(i))) for i in range(300)}
put("safetensors", "many_tensors.safetensors", safetensors(many))
deep_header = b"[" * DEEP
put("safetensors", "deep_header.safetensors", struct.pack("<Q", len(deep_header)) + deep_header)
dup = b'{"a":{"dtype":"F32","shape":[1],"data_offsets":[0,4]},"a":{"dtype":"F32","shape":[1],"data_offsets":[0,4]}}'
put("safetensors", "duplicate_names.safetensors", struct.pack("<Q", len(dup)) + dup + f32(1.0))
# One long key memoised, then set again and again (and into fresh dicts): interned, linear.
key = b"k" * 2000
rep = b"\x80\x02}X" + struct.pack("<I", len(key)) + key + b"q\x00K\x01s" + b"h\x00K\x02s" * 300
rep += b"}h\x00K\x03s" * 300 + b"."
put("pickle", "repeated_long_key.pkl", rep)
# Two entries, the first stretched (central sizes) over the second's header and data.
def overlapping_zip():
    a, b = b"a" * 64, b"hello"
    def local(name, data, descriptor):
        flags = 8 if descriptor else 0
        crc, size = (0, 0) if descriptor else (zlib.crc32(data), len(data))
        return struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, flags, 0, 0, 0, crc, size, size, len(name), 0) + name + data
    la = local(b"a", a, True) + struct.pack("<IIII", 0x08074B50, zlib.crc32(a), len(a), len(a))
    lb = local(b"b", b, False)
    stretched = len(la) - 30 - 1 + len(lb)  # from a's data to the end of b's data
    def central(name, flags, crc, size, offset):
        return struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, flags, 0, 0, 0, crc, size, size, len(name),
                           0, 0, 0, 0, 0, offset) + name
    cd = central(b"a", 8, zlib.crc32(a), stretched, 0) + central(b"b", 0, zlib.crc32(b), len(b), len(la))
    body = la + lb
    return body + cd + struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, 2, 2, len(cd), len(body), 0)
put("zip", "overlapping_entries.zip", overlapping_zip())
# A baseline JPEG whose scan is cut at half before a well-placed end-of-image marker.
jpg_seed = (OUT / "image" / "rgb_32x32_q30.jpg.in").read_bytes()
sos = jpg_seed.rfind(b"\xff\xda")
data_start = sos + 2 + struct.unpack(">H", jpg_seed[sos + 2:sos + 4])[0]
cut = data_start + (len(jpg_seed) - 2 - data_start) // 2
cut -= jpg_seed[cut - 1] == 0xFF
put("image", "rgb_32x32_q30_scan_cut.jpg.in", jpg_seed[:cut] + b"\xff\xd9")
put("image", "strip_1x17000.png.in", bytes([CONVERT | RESIZE | TARGET]) + png(17000, 1, 0, 8))

if __name__ == "__main__":
    for d in sorted(OUT.iterdir()):
        print(f"{d.name}: {len(list(d.iterdir()))} files, {sum(f.stat().st_size for f in d.iterdir())} bytes")
