#!/usr/bin/python3
"""Reference data for epona's pose inputs (tests/data/poses/).

Run with Debian's interpreter (torch 1.13 + numpy):  /usr/bin/python3 scripts/make_pose_fixtures.py

Writes
  relative_pose.json   absolute 4x4 ego-to-world poses built from random quaternions (scalar
                       last, as SciPy's Rotation.from_quat) and the relative motions computed in
                       float32 with torch.linalg.inv exactly as sampling-and-rollout.md section 7
                       describes (get_rel_pose, get_rel_traj, get_rel_traj_test), plus a case with
                       nuPlan-scale world coordinates whose reference is float64.
  npy/*.npy            files written by numpy itself (format versions 1.0/2.0/3.0, f2/f4/f8,
                       0-d, empty) and the unsupported kinds (Fortran order, big endian, int64,
                       structured) for the reader's tests; npy/values.json says what they hold.
  demo*/pose.npy, yaw.npy   the official demo's inputs in the accepted shapes, and broken ones.
  absolute_*.npy       the absolute poses of relative_pose.json as (N,4,4) f4 and (1,N,4,4) f8.
Everything is seeded; re-running reproduces the files byte for byte.
"""
import json
import os
import shutil

import numpy as np
import torch

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests", "data", "poses")
rng = np.random.default_rng(20250)


# ---- rotations ------------------------------------------------------------------------
def quat_to_matrix(q):
    """Rotation matrix of a scalar-last quaternion (x, y, z, w), normalised first (SciPy)."""
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def quat_mul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def axis_quat(axis, angle):
    q = np.zeros(4)
    q[axis] = np.sin(angle / 2)
    q[3] = np.cos(angle / 2)
    return q


def pose_matrix(q, t):
    m = np.eye(4)
    m[:3, :3] = quat_to_matrix(q)
    m[:3, 3] = t
    return m


def driving_clip(n, origin):
    """A car-like sequence: heading random walk, small roll/pitch, 0-8 m per frame forward."""
    heading = rng.uniform(-np.pi, np.pi)
    pos = np.array(origin, dtype=np.float64)
    out = []
    for _ in range(n):
        q = quat_mul(axis_quat(2, heading),
                     quat_mul(axis_quat(1, rng.normal(0, 0.01)), axis_quat(0, rng.normal(0, 0.01))))
        q *= rng.uniform(0.5, 2.0)  # unnormalised on purpose: from_quat normalises
        out.append(pose_matrix(q, pos))
        step = np.array([rng.uniform(0, 8), rng.normal(0, 0.2), rng.normal(0, 0.05)])
        pos = pos + quat_to_matrix(q) @ step
        heading += np.deg2rad(rng.normal(0, 3))
    return np.stack(out)


def random_clip(n):
    """Arbitrary 3-D rotations and translations within +-60 m."""
    return np.stack([pose_matrix(rng.normal(size=4), rng.uniform(-60, 60, size=3)) for _ in range(n)])


# ---- the reference computation (section 7), torch float32 -------------------------------
def relative(R_from, t_from, R_to, t_to):
    """Pose of `to` in the frame of `from`: (x, y) of R_from^-1 (t_to - t_from), yaw of R_from^-1 R_to."""
    inv = torch.linalg.inv(R_from)
    R_rel = inv @ R_to
    t_rel = (inv @ (t_to - t_from).unsqueeze(-1)).squeeze(-1)
    yaw = torch.atan2(R_rel[..., 1, 0], R_rel[..., 0, 0]) * 180 / np.pi
    return t_rel[..., :2], yaw.unsqueeze(-1)


def split(P):
    return P[..., :3, :3], P[..., :3, 3]


def get_rel_pose(P):  # (B, N, 4, 4) -> (B, N, 2), (B, N, 1)
    P = torch.cat([P[:, :1], P], dim=1)
    R, t = split(P)
    return relative(R[:, :-1], t[:, :-1], R[:, 1:], t[:, 1:])


def get_rel_traj(P, F, N):  # (B, F+N, 4, 4) -> (B, F, N, 2), (B, F, N, 1)
    R, t = split(P)
    poses, yaws = [], []
    for f in range(F):
        p, y = relative(R[:, f:f + 1].expand(-1, N, -1, -1), t[:, f:f + 1].expand(-1, N, -1),
                        R[:, f + 1:f + 1 + N], t[:, f + 1:f + 1 + N])
        poses.append(p)
        yaws.append(y)
    return torch.stack(poses, 1), torch.stack(yaws, 1)


def get_rel_traj_test(P, N):  # (N+1, 4, 4) -> (1, N, 3)
    R, t = split(P)
    p, y = relative(R[:1].expand(N, -1, -1), t[:1].expand(N, -1), R[1:N + 1], t[1:N + 1])
    return torch.cat([p, y], -1).unsqueeze(0)


def as_list(x):
    return np.asarray(x, dtype=np.float64).tolist()  # exact: every float32 is a double


# ---- writers ----------------------------------------------------------------------------
def save(path, arr, version=None):
    path = os.path.join(OUT, path)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as f:
        np.lib.format.write_array(f, np.asanyarray(arr), version=version, allow_pickle=False)


def write_json(path, obj):
    with open(os.path.join(OUT, path), "w") as f:
        json.dump(obj, f, indent=1)
        f.write("\n")


def make_relative_pose():
    n = 16
    P = np.stack([driving_clip(n, rng.uniform(-500, 500, size=3)), random_clip(n)]).astype(np.float32)
    Pt = torch.from_numpy(P)
    with torch.no_grad():
        rel_pose, rel_yaw = get_rel_pose(Pt)
        F, N = 4, 6
        traj_pose, traj_yaw = get_rel_traj(Pt[:, :F + N], F, N)
        traj_test = get_rel_traj_test(Pt[0], 15)

    # nuPlan-scale world coordinates, kept in float64; the reference is float64 throughout.
    utm = driving_clip(12, [664372.25, 3997581.5, 12.0])
    with torch.no_grad():
        u_pose, u_yaw = get_rel_pose(torch.from_numpy(utm)[None])
    utm_expected = torch.cat([u_pose, u_yaw], -1)[0]

    write_json("relative_pose.json", {
        "about": "absolute (B, N, 4, 4) float32 ego-to-world poses and torch float32 references (section 7)",
        "absolute": as_list(P),
        "rel_pose": as_list(rel_pose), "rel_yaw": as_list(rel_yaw),
        "traj": {"F": F, "N": N, "pose": as_list(traj_pose), "yaw": as_list(traj_yaw)},
        "traj_test": {"N": 15, "out": as_list(traj_test)},
        "utm": {"absolute": as_list(utm), "expected": as_list(utm_expected)},
    })
    save("absolute_n44_f4.npy", P[0])
    save("absolute_1n44_f8.npy", P[0:1].astype(np.float64))
    save("absolute_utm_n44_f8.npy", utm)
    return P


def make_npy_format_cases():
    a = (np.arange(12) * 0.25 - 1).reshape(3, 4)
    save("npy/f4_v1.npy", a.astype("<f4"), version=(1, 0))
    save("npy/f8_v2.npy", a.astype("<f8"), version=(2, 0))
    save("npy/f4_v3.npy", a.astype("<f4").reshape(3, 2, 2), version=(3, 0))
    save("npy/f2_v1.npy", a.astype("<f2").reshape(12), version=(1, 0))
    save("npy/scalar_f8.npy", np.array(3.5, dtype="<f8"))
    save("npy/empty_f4.npy", np.zeros((0, 2), dtype="<f4"))
    save("npy/fortran_f4.npy", np.asfortranarray(a.astype("<f4")))
    save("npy/bigendian_f4.npy", a.astype(">f4"))
    save("npy/int64.npy", np.arange(5, dtype="<i8"))
    save("npy/structured.npy", np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4")]))
    write_json("npy/values.json", {
        "about": "f4_v1, f8_v2, f2_v1 hold value[i] = 0.25 * i - 1 for i = 0..11 (flat C order); f4_v3 the same",
        "shapes": {"f4_v1": [3, 4], "f8_v2": [3, 4], "f4_v3": [3, 2, 2], "f2_v1": [12],
                   "scalar_f8": [], "empty_f4": [0, 2]},
    })


def make_demo_cases():
    n = 14
    pose = np.stack([rng.uniform(0, 8, n), rng.normal(0, 0.2, n)], axis=1)
    pose[0] = 0
    yaw = rng.normal(0, 2, n)
    yaw[0] = 0
    pose32, yaw32 = pose.astype(np.float32), yaw.astype(np.float32)
    save("demo_n2_f4/pose.npy", pose32)            # (N, 2): what the official loader works with
    save("demo_n2_f4/yaw.npy", yaw32)              # (N,)
    save("demo_1n2_f8/pose.npy", pose[None])       # (1, N, 2): the shape the official README documents
    save("demo_1n2_f8/yaw.npy", yaw[None, :, None])  # (1, N, 1)
    save("demo_mixed/pose.npy", pose.astype(np.float32))
    save("demo_mixed/yaw.npy", yaw[:, None])       # (N, 1) f8
    save("demo_mismatch/pose.npy", pose32)
    save("demo_mismatch/yaw.npy", yaw32[:-1])
    bad = pose32.copy()
    bad[5, 1] = np.nan
    save("demo_nan/pose.npy", bad)
    save("demo_nan/yaw.npy", yaw32)
    save("demo_badshape/pose.npy", np.zeros((n, 3), np.float32))
    save("demo_badshape/yaw.npy", yaw32)
    write_json("demo_expected.json", {
        "about": "demo_*: the float32 and float64 values the files hold, per frame (x m, y m, yaw deg)",
        "f4": {"x": as_list(pose32[:, 0]), "y": as_list(pose32[:, 1]), "yaw": as_list(yaw32)},
        "f8": {"x": as_list(pose[:, 0]), "y": as_list(pose[:, 1]), "yaw": as_list(yaw)},
    })


if __name__ == "__main__":
    shutil.rmtree(OUT, ignore_errors=True)
    os.makedirs(OUT)
    make_relative_pose()
    make_npy_format_cases()
    make_demo_cases()
    print("wrote", sorted(os.listdir(OUT)))
