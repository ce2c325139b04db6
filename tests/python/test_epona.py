"""The `epona` Python module against the C++ paths, on the conformance model (tests/data/golden:
64x128 frames, 3 condition frames) and its 3-frame demo clip (tests/data/demo), with few sampling
steps so the suite takes seconds: a plan equals the CLI's for the same seed, a session's steps
equal `rollout`'s and `predict_next`'s, frames equal `decode` of the latents, arrays have the
documented dtype and shape, and bad input raises epona.Error carrying the library's message.
Run by ctest as the test `python` (PYTHONPATH at the built module; EPONA_CLI at the CLI if built).
"""
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import epona

SOURCE = Path(os.environ.get("EPONA_SOURCE_DIR", Path(__file__).resolve().parents[2]))
GOLDEN = SOURCE / "tests/data/golden"
CLIP = SOURCE / "tests/data/demo"
STEPS = 3


@pytest.fixture(scope="module")
def model():
    return epona.load(weights=str(GOLDEN / "weights_world.safetensors"),
                      dcae=str(GOLDEN / "weights_dcae.safetensors"), config=str(GOLDEN / "configs.json"))


@pytest.fixture(scope="module")
def clip():
    frames = np.stack([epona.read_image(str(CLIP / f"frame_0{i}.png")) for i in range(3)])
    return frames, epona.load_poses(str(CLIP / "poses.csv"))


@pytest.fixture(scope="module")
def latents(model, clip):
    return model.encode(clip[0])


def test_shapes_and_dtypes(model, clip, latents):
    frames, poses = clip
    assert frames.dtype == np.uint8 and frames.shape == (3, 64, 128, 3)
    assert poses.dtype == np.float32 and poses.shape == (3, 3)
    assert model.image_size == (64, 128) and model.condition_frames == 3 and model.traj_len == 15
    assert latents.dtype == np.float32 and latents.shape == (3,) + model.latent_shape == (3, 32, 2, 4)
    assert np.isfinite(latents).all()
    images = model.decode(latents)
    assert images.dtype == np.uint8 and images.shape == (3, 64, 128, 3)
    assert model.decode(latents[:2], video=True).shape == (2, 64, 128, 3)  # one clip of the DC-AE's 2 frames
    plan = model.plan(latents, poses, steps=STEPS, seed=1)
    assert plan.dtype == np.float32 and plan.shape == (15, 3)
    latent, traj = model.predict_next(latents, poses, steps=STEPS)
    assert latent.shape == model.latent_shape and traj.shape == (15, 3)
    trajs, lats = model.rollout(latents, poses, frames=2, steps=STEPS)
    assert trajs.shape == (2, 15, 3) and lats.shape == (2, 32, 2, 4)


def test_encode_accepts_one_image_and_other_layouts(model, clip, latents):
    frames = clip[0]
    assert np.array_equal(model.encode(frames[1]), latents[1:2])
    # A non-contiguous view is converted, not misread.
    assert np.array_equal(model.encode(np.ascontiguousarray(frames[::-1])[::-1]), latents)


def test_plan_is_the_seeds_and_the_steps_first_draw(model, clip, latents):
    poses = clip[1]
    a = model.plan(latents, poses, steps=STEPS, seed=5)
    assert np.array_equal(a, model.plan(latents, poses, steps=STEPS, seed=5))
    assert not np.array_equal(a, model.plan(latents, poses, steps=STEPS, seed=6))
    # step_eval draws the trajectory noise first: predict_next's plan is plan()'s.
    _, traj = model.predict_next(latents, poses, steps=STEPS, seed=5)
    assert np.array_equal(a, traj)


def test_plan_equals_the_cli(model, clip, latents, tmp_path):
    cli = os.environ.get("EPONA_CLI")
    if not cli or not Path(cli).exists():
        pytest.skip("the epona CLI is not built in this build (EPONA_CLI unset)")
    subprocess.run([cli, "plan", "--hypotheses", "1", "--weights", str(GOLDEN / "weights_world.safetensors"),
                    "--dcae", str(GOLDEN / "weights_dcae.safetensors"), "--config", str(GOLDEN / "configs.json"),
                    "--frames", str(CLIP), "--poses", str(CLIP / "poses.csv"), "--steps", str(STEPS),
                    "--seed", "5", "--out", str(tmp_path), "--quiet"], check=True, capture_output=True)
    rows = [line.split(",") for line in (tmp_path / "trajectory.csv").read_text().splitlines()
            if line and line[0].isdigit()]
    cli_plan = np.array([[float(v) for v in r[2:5]] for r in rows], dtype=np.float32)
    # The CSV holds each float's shortest round-trip text: the two paths agree bit for bit.
    assert np.array_equal(model.plan(latents, clip[1], steps=STEPS, seed=5), cli_plan)


def test_session_steps_equal_rollout(model, clip):
    frames, poses = clip
    latents = model.encode(frames)
    trajs, lats = model.rollout(latents, poses, frames=3, steps=STEPS, seed=7)
    session = epona.WorldSession(model, steps=STEPS, seed=7)
    session.reset(frames, poses)
    decoded = model.decode(lats)  # each latent alone, as a session decodes its frame
    for i in range(3):
        frame, traj = session.step()
        assert frame.dtype == np.uint8 and frame.shape == (64, 128, 3)
        assert np.array_equal(traj, trajs[i])
        assert np.array_equal(frame, decoded[i])
    assert session.steps_taken == 3
    window_latents, window_poses = session.window()
    assert np.array_equal(window_latents, lats)  # three steps replaced the whole window
    assert np.array_equal(window_poses, trajs[:, 0, :])  # slid in: waypoint 0 of each plan


def test_session_step_with_an_action_equals_predict_next(model, clip, latents):
    frames, poses = clip
    session = epona.WorldSession(model, steps=STEPS, seed=3)
    session.reset(frames, poses)
    window_latents, window_poses = session.window()
    assert np.array_equal(window_latents, latents)
    assert window_poses[0].tolist() == [0, 0, 0]  # the window's first frame gets no motion (as the CLI)
    assert np.array_equal(window_poses[1:], poses[1:])
    action = np.array([1.5, 0.2, 3.0], dtype=np.float32)
    latent, traj = model.predict_next(latents, poses, action=action, steps=STEPS, seed=3)
    assert traj is None
    frame, traj = session.step([1.5, 0.2, 3.0])  # a list works as well as an array
    assert traj is None
    assert np.array_equal(frame, model.decode(latent[None])[0])
    window_latents, window_poses = session.window()
    assert np.array_equal(window_latents[-1], latent)
    assert np.array_equal(window_poses[-1], action)
    assert np.array_equal(window_latents[:-1], latents[1:])


def test_session_steps_keep_the_workspace(model, clip):
    session = epona.WorldSession(model, steps=STEPS)
    session.reset(*clip)
    session.step()
    capacity = session.arena_capacity
    assert capacity > 0
    for action in (None, (2.0, 0.0, 0.0), None):
        session.step(action)
        assert session.arena_capacity == capacity
    session.reset(*clip)
    assert session.steps_taken == 0


def test_threads_share_a_model(model, clip, latents):
    expected = model.plan(latents, clip[1], steps=STEPS, seed=9)
    results = [None] * 4

    def run(i):
        results[i] = model.plan(latents, clip[1], steps=STEPS, seed=9)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(np.array_equal(r, expected) for r in results)


def test_the_gil_is_released_while_the_model_computes(model, clip, latents):
    # A rollout in a thread while this thread waits for it to begin. Holding the GIL through the
    # call, the rollout would end before this thread ran again; released, this thread runs again
    # while it computes, about a switch interval (5 ms) after it began. One moment is compared,
    # not the longest pause over the whole rollout: only this thread kept off the CPU for half
    # the rollout right at its start could fail it by chance.
    began, span = threading.Event(), {}

    def work():
        span["start"] = time.perf_counter()
        began.set()
        model.rollout(latents, clip[1], frames=4, steps=100)
        span["end"] = time.perf_counter()

    worker = threading.Thread(target=work)
    worker.start()
    began.wait()
    resumed = time.perf_counter()
    worker.join()
    took = span["end"] - span["start"]
    assert resumed - span["start"] < took / 2, (
        f"this thread ran again {resumed - span['start']:.3f} s into a {took:.3f} s rollout")


def test_errors_carry_the_library_message(model, clip, latents):
    frames, poses = clip
    assert issubclass(epona.Error, RuntimeError)
    session = epona.WorldSession(model, steps=STEPS)
    with pytest.raises(epona.Error, match=r"call reset\(\)"):
        session.step()
    with pytest.raises(epona.Error, match=r"2 frame\(s\) given; the model needs 3"):
        session.reset(frames[:2], poses)
    with pytest.raises(epona.Error, match="frame 0 is 32x64; the model takes 64x128"):
        session.reset(np.zeros((3, 32, 64, 3), np.uint8), poses)
    with pytest.raises(epona.Error, match=r"uint8 \(N, H, W, 3\)"):
        session.reset(np.zeros((3, 64, 128), np.uint8), poses)
    bad = poses.copy()
    bad[1, 2] = math.nan
    with pytest.raises(epona.Error, match="pose 1 .* non-finite"):
        session.reset(frames, bad)
    with pytest.raises(epona.Error, match=r"poses must be float \(F, 3\)"):
        session.reset(frames, poses[:, :2])
    session.reset(frames, poses)
    with pytest.raises(epona.Error, match="3 values"):
        session.step([1.0, 2.0])
    with pytest.raises(epona.Error, match="non-finite"):
        session.step([1.0, math.inf, 0.0])
    assert session.steps_taken == 0
    with pytest.raises(epona.Error, match="latents"):
        model.plan(latents[:, :16], poses)
    with pytest.raises(epona.Error, match=r"poses hold 2 row\(s\)"):
        model.plan(latents, poses[:2])
    with pytest.raises(epona.Error, match="sampling steps"):
        model.plan(latents, poses, steps=0)
    with pytest.raises(epona.Error, match="no such file"):
        epona.load(weights=str(GOLDEN / "missing.safetensors"), dcae=str(GOLDEN / "weights_dcae.safetensors"))
    with pytest.raises(epona.Error, match="dtype 'int8': one of 'float32', 'bfloat16'"):
        epona.load(dtype="int8")
    with pytest.raises(epona.Error, match="backend 'tpu': one of 'cpu', 'cuda'"):
        epona.load(backend="tpu")
    with pytest.raises(epona.Error, match="choose 'best': one of 'medoid', 'mean'"):
        model.plan(latents, poses, steps=STEPS, hypotheses=2, choose="best")
    with pytest.raises(epona.Error, match="unknown solver 'rk4'"):
        model.plan(latents, poses, steps=STEPS, solver="rk4")
    with pytest.raises(epona.Error, match=r"plan hypotheses must be in \[1, 1024\], got 0"):
        model.plan(latents, poses, steps=STEPS, hypotheses=0)


def test_bundled_model_loads_by_default(clip):
    bundled = epona.load()
    assert Path(bundled.world_file).parent == Path(epona.bundled_model_dir)
    assert bundled.image_size == (256, 512) and bundled.condition_frames == 10
    demo = Path(epona.bundled_model_dir) / "demo"
    frame = epona.read_image(str(sorted((demo / "frames").glob("*.png"))[-1]))
    assert frame.shape == (256, 512, 3)
    z = bundled.encode(frame)
    assert z.shape == (1,) + bundled.latent_shape
    # A planning step on a still window: 10 copies of the last frame, standing.
    plan = bundled.plan(np.repeat(z, 10, axis=0), np.zeros((10, 3), np.float32), steps=2)
    assert plan.shape == (15, 3) and np.isfinite(plan).all()
    assert bundled.recommended_planning == (8, "mean")  # its configs.json "planner", as the CLI's plan uses


def test_the_session_example_runs(tmp_path):
    # examples/python/session.py on the bundled model, one sampling step a frame (seconds).
    out = tmp_path / "session.png"
    run = subprocess.run([sys.executable, str(SOURCE / "examples/python/session.py"), str(out), "--steps", "1",
                          "--frames", "2"], capture_output=True, text=True, env=dict(os.environ))
    assert run.returncode == 0, run.stderr
    assert "step 0: planned" in run.stdout and "step 1: drove the given action" in run.stdout
    strip = epona.read_image(str(out))
    assert strip.shape == (256, 3 * 512, 3)


# ---- backends and weight types -------------------------------------------------------------

def relative(a, b):
    """The relative L2 difference of a from b."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-12))


def load_golden(**kwargs):
    return epona.load(weights=str(GOLDEN / "weights_world.safetensors"),
                      dcae=str(GOLDEN / "weights_dcae.safetensors"), config=str(GOLDEN / "configs.json"), **kwargs)


# CPU bf16 weights against float32 (activations stay float32 on the CPU): the plan within 1e-2
# relative (L2 over the trajectory), the latents within 2e-2, the decoded images within 1 grey
# level on average. Measured on this model: 1.2e-3..1.7e-3 (plans of seeds 0-5), 3.9e-3, 0.16.
BF16_PLAN, BF16_LATENT, BF16_IMAGE_MEAN = 1e-2, 2e-2, 1.0
# The GPU's bf16 keeps activations in bf16 as well (docs/cuda.md): five times the bounds, but
# the plan still within 5e-2 relative of the CPU's float32 plan.
CUDA_BF16_PLAN, CUDA_BF16_LATENT, CUDA_BF16_IMAGE_MEAN = 5 * BF16_PLAN, 5 * BF16_LATENT, 5 * BF16_IMAGE_MEAN


@pytest.fixture(scope="module")
def model_bf16():
    return load_golden(dtype="bfloat16")


def test_the_model_says_its_backend_and_dtype(model, model_bf16):
    assert (model.backend, model.dtype) == ("cpu", "float32")
    assert model.recommended_planning == (1, "medoid")  # the conformance model recommends none
    assert (model_bf16.backend, model_bf16.dtype) == ("cpu", "bfloat16")
    assert load_golden(dtype="bf16").dtype == "bfloat16"  # the CLI's short name too


def test_cpu_bf16_is_close_to_float32(model, model_bf16, clip, latents):
    frames, poses = clip
    z = model_bf16.encode(frames)
    assert z.dtype == np.float32 and z.shape == latents.shape and np.isfinite(z).all()
    assert relative(z, latents) < BF16_LATENT
    plan = model_bf16.plan(latents, poses, steps=STEPS, seed=5)
    assert np.isfinite(plan).all()
    assert relative(plan, model.plan(latents, poses, steps=STEPS, seed=5)) < BF16_PLAN
    images = model_bf16.decode(latents)
    assert np.abs(images.astype(np.int16) - model.decode(latents)).mean() < BF16_IMAGE_MEAN


def test_cpu_bf16_session_steps(model_bf16, clip):
    session = epona.WorldSession(model_bf16, steps=STEPS, seed=2)
    session.reset(*clip)
    frame, traj = session.step()
    assert frame.shape == (64, 128, 3) and traj.shape == (15, 3) and np.isfinite(traj).all()
    frame, traj = session.step((1.0, 0.0, 0.0))
    assert traj is None and session.steps_taken == 2


def test_plan_hypotheses_and_the_chosen_plan(model, clip, latents):
    poses = clip[1]
    fan = model.plan_hypotheses(latents, poses, 4, steps=STEPS, seed=5)
    assert fan.shape == (4, 15, 3) and np.isfinite(fan).all()
    # Row 0 draws plan()'s noise; the K plans run as one batch, so equal within float rounding.
    np.testing.assert_allclose(fan[0], model.plan(latents, poses, steps=STEPS, seed=5), rtol=1e-5, atol=1e-5)
    assert not np.array_equal(fan[0], fan[1])
    mean = model.plan(latents, poses, steps=STEPS, seed=5, hypotheses=4, choose="mean")
    np.testing.assert_allclose(mean, fan.astype(np.float64).mean(axis=0), rtol=1e-6, atol=1e-6)
    medoid = model.plan(latents, poses, steps=STEPS, seed=5, hypotheses=4)  # the default rule
    assert any(np.array_equal(medoid, row) for row in fan)


def test_the_solver_is_chosen_by_name(model, clip, latents):
    poses = clip[1]
    euler = model.plan(latents, poses, steps=STEPS, seed=5)
    assert np.array_equal(euler, model.plan(latents, poses, steps=STEPS, seed=5, solver="euler"))
    heun = model.plan(latents, poses, steps=STEPS, seed=5, solver="heun")
    assert np.isfinite(heun).all() and not np.array_equal(heun, euler)
    session = epona.WorldSession(model, steps=STEPS, seed=5, solver="midpoint")
    session.reset(*clip)
    assert np.isfinite(session.step()[1]).all()


# ---- CUDA ----------------------------------------------------------------------------------

def cuda_missing():
    """Why backend="cuda" cannot run here, or None."""
    if not epona.built_with_cuda:
        return "the epona module was built without CUDA (configure with -DEPONA_CUDA=ON -DEPONA_PYTHON=ON)"
    if not epona.cuda_available():
        return "no CUDA device is present"
    return None


# CUDA float32 against the CPU's: 1e-4 relative for one step (the GPU matches the CPU within 1e-5
# per stage, docs/cuda.md); steps after the first see generated frames: the golden set's rollout
# tolerance, 1e-3.
ROLLOUT = 1e-3

needs_cuda = pytest.mark.skipif(cuda_missing() is not None, reason=f"backend='cuda': {cuda_missing()}")


def test_cuda_without_it_is_an_epona_error():
    if cuda_missing() is None:
        pytest.skip("CUDA is available here: nothing to refuse")
    with pytest.raises(epona.Error, match="built without CUDA" if not epona.built_with_cuda else "no CUDA device"):
        load_golden(backend="cuda")


@pytest.fixture(scope="module")
def cuda_model():
    return load_golden(backend="cuda")


@pytest.fixture(scope="module")
def cuda_bf16():
    return load_golden(backend="cuda", dtype="bfloat16")


@needs_cuda
def test_cuda_float32_equals_the_cpu(model, cuda_model, clip, latents):
    frames, poses = clip
    assert (cuda_model.backend, cuda_model.dtype) == ("cuda", "float32")
    # The GPU's float32 matches the CPU within 1e-5 per stage (docs/cuda.md); 1e-4 over the chain.
    z = cuda_model.encode(frames)
    assert relative(z, latents) < 1e-4
    for seed in (1, 5):
        assert relative(cuda_model.plan(latents, poses, steps=STEPS, seed=seed),
                        model.plan(latents, poses, steps=STEPS, seed=seed)) < 1e-4
    latent, traj = cuda_model.predict_next(latents, poses, steps=STEPS, seed=3)
    cpu_latent, cpu_traj = model.predict_next(latents, poses, steps=STEPS, seed=3)
    assert relative(latent, cpu_latent) < 1e-4 and relative(traj, cpu_traj) < 1e-4
    latent, _ = cuda_model.predict_next(latents, poses, action=(1.0, 0.1, 2.0), steps=STEPS, seed=3)
    assert relative(latent, model.predict_next(latents, poses, action=(1.0, 0.1, 2.0), steps=STEPS, seed=3)[0]) < 1e-4
    # Later steps see generated frames: 1e-3, the golden set's rollout tolerance (tests/cuda/world_parity.cu).
    trajs, lats = cuda_model.rollout(latents, poses, frames=2, steps=STEPS, seed=7)
    cpu_trajs, cpu_lats = model.rollout(latents, poses, frames=2, steps=STEPS, seed=7)
    assert relative(trajs[0], cpu_trajs[0]) < 1e-4 and relative(lats[0], cpu_lats[0]) < 1e-4
    assert relative(trajs, cpu_trajs) < ROLLOUT and relative(lats, cpu_lats) < ROLLOUT
    # Images: a float difference of 1e-5 may move a value across a rounding boundary.
    for video in (False, True):
        diff = np.abs(cuda_model.decode(latents[:2], video=video).astype(np.int16) - model.decode(latents[:2], video=video))
        assert diff.max() <= 2 and diff.mean() < 0.05


@needs_cuda
def test_cuda_hypotheses_equal_the_cpu(model, cuda_model, clip, latents):
    poses = clip[1]
    fan = cuda_model.plan_hypotheses(latents, poses, 4, steps=STEPS, seed=5)
    assert relative(fan, model.plan_hypotheses(latents, poses, 4, steps=STEPS, seed=5)) < 1e-4


@needs_cuda
def test_cuda_session_steps_as_the_cpu(model, cuda_model, clip):
    sessions = [epona.WorldSession(m, steps=STEPS, seed=7) for m in (cuda_model, model)]
    for s in sessions:
        s.reset(*clip)
    for i, action in enumerate((None, (1.5, 0.2, 3.0), None)):
        (frame, traj), (cpu_frame, cpu_traj) = (s.step(action) for s in sessions)
        assert frame.shape == (64, 128, 3) and frame.dtype == np.uint8
        assert np.abs(frame.astype(np.int16) - cpu_frame).max() <= (2 if i == 0 else 4)
        assert (traj is None) == (action is not None)
        if traj is not None:
            assert relative(traj, cpu_traj) < (1e-4 if i == 0 else ROLLOUT)
    assert sessions[0].steps_taken == 3
    assert relative(sessions[0].window()[0], sessions[1].window()[0]) < ROLLOUT


@needs_cuda
def test_cuda_bf16_runs_and_is_close(model, cuda_bf16, clip, latents):
    frames, poses = clip
    assert (cuda_bf16.backend, cuda_bf16.dtype) == ("cuda", "bfloat16")
    z = cuda_bf16.encode(frames)
    assert np.isfinite(z).all() and relative(z, latents) < CUDA_BF16_LATENT
    plan = cuda_bf16.plan(latents, poses, steps=STEPS, seed=5)
    assert np.isfinite(plan).all()
    assert relative(plan, model.plan(latents, poses, steps=STEPS, seed=5)) < CUDA_BF16_PLAN
    images = cuda_bf16.decode(latents)
    assert np.abs(images.astype(np.int16) - model.decode(latents)).mean() < CUDA_BF16_IMAGE_MEAN
    session = epona.WorldSession(cuda_bf16, steps=STEPS, seed=2)
    session.reset(frames, poses)
    frame, traj = session.step()
    assert frame.shape == (64, 128, 3) and np.isfinite(traj).all()
