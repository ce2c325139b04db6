#!/usr/bin/python3
"""Writes the torch.save fixtures of tests/io/torch_checkpoint.cpp into tests/data/pkl/.

Run with Debian's /usr/bin/python3 (it has torch; the pyenv python3 on PATH does not):
    /usr/bin/python3 scripts/make_pkl_fixtures.py

Every fixture is written by torch.save itself (except the re-packed ZIP64 archives and the
hostile pickle, built here byte by byte) and read back with torch.load(weights_only=True).
expected.txt lists, for every tensor the C++ reader must return, its file, key, dtype, shape and
raw element bits (hex; int64 in decimal), one tensor per line, tab-separated:
    file  key  dtype  [d0,d1,...]  v0 v1 ...
The golden conformance weights are converted to .pkl (read with a small safetensors parser,
no safetensors package); the C++ test compares those with the .safetensors files directly.
"""
import collections
import io
import json
import os
import struct
import sys
import zipfile
import zlib

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(ROOT, "tests", "data", "pkl")
GOLDEN = os.path.join(ROOT, "tests", "data", "golden")
DTYPE_NAME = {torch.float32: "float32", torch.bfloat16: "bfloat16", torch.float16: "float16", torch.int64: "int64"}
BITS_VIEW = {torch.float32: torch.int32, torch.bfloat16: torch.int16, torch.float16: torch.int16}

expected_lines = []


def element_bits(t):
    """The raw bits of every element, as text: hex for floats (exact), decimal for int64."""
    flat = t.contiguous().reshape(-1)
    if t.dtype == torch.int64:
        return [str(int(v)) for v in flat.tolist()]
    width = 8 if t.dtype == torch.float32 else 4
    mask = (1 << (4 * width)) - 1
    return [format(int(v) & mask, "0%dx" % width) for v in flat.view(BITS_VIEW[t.dtype]).tolist()]


def expect(file, state):
    for key, t in state.items():
        shape = "[" + ",".join(str(d) for d in t.shape) + "]"
        values = " ".join(element_bits(t.detach()))
        expected_lines.append("\t".join([file, key, DTYPE_NAME[t.dtype], shape, values]))


def check_reloads(path, state, key=None):
    # torch 1.13's weights_only unpickler lacks BINFLOAT; files with float entries load fully.
    with zipfile.ZipFile(path) as z:
        has_float = any(b"G" in z.read(n) for n in z.namelist() if n.endswith("data.pkl"))
    obj = torch.load(path, weights_only=not has_float)
    got = obj[key] if key else obj
    assert list(got.keys()) == list(state.keys()), path
    for k in state:
        assert got[k].dtype == state[k].dtype and torch.equal(bits(got[k]), bits(state[k])), (path, k)


def bits(t):
    """The tensor's raw bits as integers, so that NaN compares equal to itself."""
    t = t.detach().contiguous()
    return t if t.dtype == torch.int64 else t.view(BITS_VIEW[t.dtype])


def save(file, obj, state, key=None, expect_values=True):
    path = os.path.join(OUT, file)
    torch.save(obj, path)
    check_reloads(path, state, key)
    if expect_values:
        expect(file, state)
    return path


def small_module():
    torch.manual_seed(0)
    return torch.nn.Sequential(
        torch.nn.Conv2d(3, 4, 3, padding=1),
        torch.nn.BatchNorm2d(4),   # running stats + int64 num_batches_tracked
        torch.nn.Flatten(),
        torch.nn.Linear(4 * 2 * 2, 5),
        torch.nn.LayerNorm(5),
    )


def plain_fp32():
    torch.manual_seed(1)
    state = {
        "linear.weight": torch.randn(3, 4),
        "linear.bias": torch.randn(3),
        "conv.weight": torch.randn(2, 3, 3, 3),
        "scale": torch.tensor(0.25),                  # 0-d
        "empty": torch.zeros(0, 3),                   # no elements
        "special": torch.tensor([float("inf"), -float("inf"), float("nan"), -0.0, 1e-45]),
        "steps": torch.tensor(7, dtype=torch.int64),
        "ids": torch.arange(-3, 3, dtype=torch.int64).reshape(2, 3),
    }
    save("fp32_plain.pkl", state, state)


def world_bf16():
    torch.manual_seed(2)
    state = collections.OrderedDict()
    state["module.model.time_emb"] = torch.randn(5, 8).to(torch.bfloat16)
    state["module.model.img_projector.0.weight"] = torch.randn(8, 4).to(torch.bfloat16)
    state["module.dit.img_in.weight"] = torch.randn(6, 4).to(torch.bfloat16)
    state["module.dit.img_in.bias"] = torch.randn(6).to(torch.bfloat16)
    state["module.traj_dit.final_layer.linear.weight"] = torch.randn(3, 6).to(torch.bfloat16)
    obj = {"model_state_dict": state, "epoch": 7, "lr": 1e-4, "note": "bf16 training run",
           "flags": [True, False, None], "betas": (0.9, 0.999)}
    save("bf16_world.pkl", obj, state, key="model_state_dict")
    return obj, state


def dcae_fp16():
    m = small_module().half()
    state = m.state_dict()   # an OrderedDict with _metadata: pickled with BUILD
    obj = {"model": state, "step": 20000}
    save("fp16_dcae.pkl", obj, state, key="model")


def ordered_state_dict():
    m = small_module()
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.5)
    state = m.state_dict()
    # Saved through a buffer: the archive folder is then "archive", not the file stem.
    buf = io.BytesIO()
    torch.save(state, buf)
    path = os.path.join(OUT, "ordered_state_dict.pkl")
    with open(path, "wb") as f:
        f.write(buf.getvalue())
    check_reloads(path, state)
    expect("ordered_state_dict.pkl", state)


def views_and_sharing():
    torch.manual_seed(3)
    base = torch.randn(100)
    matrix = torch.randn(6, 4)
    linear = torch.nn.Linear(4, 2)
    state = collections.OrderedDict()
    state["base"] = base                          # the whole storage
    state["slice"] = base[10:30]                  # storage offset 10
    state["window"] = base[30:40].view(2, 5)      # offset 30, 2-D view
    state["element"] = base[5]                    # 0-d at offset 5
    state["rows"] = matrix[2:4]                   # contiguous rows of a 2-D storage (offset 8)
    state["alias"] = base                         # the same tensor object twice (pickle memo)
    state["param.weight"] = linear.weight         # nn.Parameter: _rebuild_parameter
    state["param.bias"] = linear.bias
    state["unit_dims"] = matrix[1:2, :].unsqueeze(0)   # shape (1, 1, 4): size-1 dims, offset 4
    save("views.pkl", state, state)


def noncontiguous():
    torch.manual_seed(4)
    state = {"ok": torch.randn(2, 2), "transposed": torch.randn(3, 4).t()}
    torch.save(state, os.path.join(OUT, "noncontiguous.pkl"))


def no_state_dict():
    obj = {"epoch": 3, "config": {"lr": 0.1, "name": "run"}, "model": "dcae"}
    torch.save(obj, os.path.join(OUT, "no_state_dict.pkl"))


# ---- ZIP64 re-packs -----------------------------------------------------------------------

FIXED_TIME = (2025, 1, 1, 0, 0, 0)


def repack_force_zip64(src, dst):
    """Python's zipfile, force_zip64=True: ZIP64 extra fields in every local header."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_STORED) as zout:
        for info in zin.infolist():
            out = zipfile.ZipInfo(info.filename, date_time=FIXED_TIME)
            out.compress_type = zipfile.ZIP_STORED
            with zout.open(out, "w", force_zip64=True) as f:
                f.write(zin.read(info.filename))


def repack_full_zip64(src, dst):
    """Hand-built: every size and offset saturated in both headers and carried by ZIP64 extra
    fields, a ZIP64 end record and locator, and an end record with every field saturated."""
    with zipfile.ZipFile(src) as zin:
        records = [(i.filename, zin.read(i.filename)) for i in zin.infolist()]
    out = bytearray()
    central = bytearray()
    for name, data in records:
        n = name.encode()
        crc = zlib.crc32(data) & 0xFFFFFFFF
        offset = len(out)
        local_extra = struct.pack("<HHQQ", 1, 16, len(data), len(data))
        out += struct.pack("<IHHHHHIIIHH", 0x04034B50, 45, 0, 0, 0, 0x21, crc, 0xFFFFFFFF, 0xFFFFFFFF,
                           len(n), len(local_extra)) + n + local_extra + data
        central_extra = struct.pack("<HHQQQ", 1, 24, len(data), len(data), offset)
        central += struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 45, 45, 0, 0, 0, 0x21, crc, 0xFFFFFFFF,
                               0xFFFFFFFF, len(n), len(central_extra), 0, 0, 0, 0, 0xFFFFFFFF) + n + central_extra
    cd_offset = len(out)
    out += central
    zip64_end = len(out)
    out += struct.pack("<IQHHIIQQQQ", 0x06064B50, 44, 45, 45, 0, 0, len(records), len(records), len(central), cd_offset)
    out += struct.pack("<IIQI", 0x07064B50, 0, zip64_end, 1)
    out += struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, 0xFFFF, 0xFFFF, 0xFFFFFFFF, 0xFFFFFFFF, 0)
    with open(dst, "wb") as f:
        f.write(out)


def zip64_fixtures(src_path, state):
    for name, repack in [("zip64_local.pkl", repack_force_zip64), ("zip64_full.pkl", repack_full_zip64)]:
        dst = os.path.join(OUT, name)
        repack(src_path, dst)
        with zipfile.ZipFile(dst) as z:   # Python's reader accepts it ...
            assert z.testzip() is None
        check_reloads(dst, state, key="model_state_dict")   # ... and so does torch.load
        expect(name, state)


# ---- hostile --------------------------------------------------------------------------------

def hostile_os_system():
    """A pickle whose only object is the global os.system (protocol 2 GLOBAL opcode written by
    hand). It calls nothing: even Python's own unpickler would just return the function; our
    reader must refuse the global by name."""
    pkl = b"\x80\x02" + b"cos\nsystem\n" + b"q\x00" + b"."
    path = os.path.join(OUT, "hostile_os_system.pkl")
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        z.writestr(zipfile.ZipInfo("hostile_os_system/data.pkl", date_time=FIXED_TIME), pkl)
        z.writestr(zipfile.ZipInfo("hostile_os_system/version", date_time=FIXED_TIME), b"3\n")
    try:
        torch.load(path, weights_only=True)
        raise AssertionError("torch.load(weights_only=True) accepted os.system")
    except pickle_error_types() as e:
        assert "system" in str(e), e


def pickle_error_types():
    import pickle
    return (pickle.UnpicklingError, RuntimeError)


# ---- golden weights -> .pkl -----------------------------------------------------------------

def read_safetensors(path):
    """A minimal safetensors reader (8-byte header length, JSON header, raw little-endian data)."""
    with open(path, "rb") as f:
        blob = f.read()
    (n,) = struct.unpack("<Q", blob[:8])
    header = json.loads(blob[8:8 + n])
    data = blob[8 + n:]
    dtypes = {"F32": torch.float32, "I64": torch.int64, "BF16": torch.bfloat16, "F16": torch.float16}
    state = collections.OrderedDict()
    for key, info in header.items():
        if key == "__metadata__":
            continue
        begin, end = info["data_offsets"]
        raw = bytearray(data[begin:end])
        t = torch.frombuffer(raw, dtype=dtypes[info["dtype"]]) if raw else torch.empty(0, dtype=dtypes[info["dtype"]])
        state[key] = t.reshape(info["shape"]).clone()
    return state


def golden_weights():
    for src, dst, key in [("weights_world.safetensors", "weights_world.pkl", "model_state_dict"),
                          ("weights_dcae.safetensors", "weights_dcae.pkl", "model")]:
        state = read_safetensors(os.path.join(GOLDEN, src))
        save(dst, {key: state}, state, key=key, expect_values=False)


def main():
    if not os.path.isdir(GOLDEN):
        sys.exit("golden data not found at " + GOLDEN)
    os.makedirs(OUT, exist_ok=True)
    plain_fp32()
    _, world_state = world_bf16()
    dcae_fp16()
    ordered_state_dict()
    views_and_sharing()
    noncontiguous()
    no_state_dict()
    zip64_fixtures(os.path.join(OUT, "bf16_world.pkl"), world_state)
    hostile_os_system()
    golden_weights()
    with open(os.path.join(OUT, "expected.txt"), "w") as f:
        f.write("\n".join(expected_lines) + "\n")
    total = sum(os.path.getsize(os.path.join(OUT, p)) for p in os.listdir(OUT))
    print("wrote %d files, %.2f MB, into %s" % (len(os.listdir(OUT)), total / 1e6, OUT))


if __name__ == "__main__":
    main()
