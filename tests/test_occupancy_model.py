"""The learned occupancy: its input grid, the network, the shipped checkpoint, training, and
the evaluation's scoring."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from mapper.grid import FREE, OCCUPIED, GridSpec, OccupancyGrid
from mapper.integrate import backproject
from mapper.model import (
    IN_CHANNELS,
    OccupancyNet,
    WindowSpec,
    crop,
    encode,
    load_checkpoint,
    shipped_checkpoint,
)
from mapper.predictor import OccupancyPredictor
from mission.learning.evaluate import Counts, heightmap_completion, score_maps
from mission.learning.training import TrainConfig, gather_world, make_batch, masked_loss, train
from rovergate.errors import CheckpointError, ConfigError
from rovergate.geometry import R_BODY_OPTICAL
from rovergate.types import CameraIntrinsics


def _camera_looking_along_x(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R_BODY_OPTICAL
    T[:3, 3] = [x, y, z]
    return T


def test_depth_marks_returns_occupied_the_way_there_free_and_nothing_behind():
    spec = GridSpec((-2.0, -5.0, -5.0), 0.5, (30, 20, 20))
    grid = OccupancyGrid(spec, ray_stride_px=1)
    k = CameraIntrinsics.from_fov(16, 12, 20.0)
    depth = np.full((12, 16), 6.0, dtype=np.float32)  # a wall at x = 6
    depth[:, :8] = np.nan  # no return on the left half: no evidence there
    grid.integrate(depth, k, _camera_looking_along_x(0.0, 0.0, 0.0))
    wall = np.array([[6.0, -0.3, 0.0]])
    before = np.array([[3.0, -0.3, 0.0], [1.0, -0.1, 0.0]])
    behind = np.array([[8.0, -0.3, 0.0]])
    left = np.array([[3.0, 0.5, 0.0]])  # y > 0 is the image's left half
    ijk = lambda p: tuple(spec.index(p)[0][0])  # noqa: E731
    assert grid.state[ijk(wall)] & OCCUPIED
    assert all(grid.state[ijk(p[None])] == FREE for p in before)
    assert grid.state[ijk(behind)] == 0 and grid.state[ijk(left)] == 0
    assert grid.known(np.vstack([wall, before, behind, left])).tolist() == [
        True, True, True, False, False]


def test_crop_reads_outside_the_volume_as_fill():
    v = np.arange(27, dtype=np.uint8).reshape(3, 3, 3)
    c = crop(v, np.array([-1, 1, 0]), (2, 2, 2), fill=9)
    assert c[0].tolist() == [[9, 9], [9, 9]]
    assert c[1].tolist() == v[0, 1:3, 0:2].tolist()


def test_forward_pass_on_a_known_input():
    torch.manual_seed(0)
    model = OccupancyNet().eval()
    state = np.zeros((16, 16, 8), dtype=np.uint8)
    state[:, :, 2] = OCCUPIED
    x = torch.from_numpy(encode(state, below=4))[None]
    assert x.shape == (1, IN_CHANNELS, 16, 16, 8)
    assert x[0, 0, :, :, 2].all() and not x[0, 0, :, :, 3].any()  # occupied channel
    assert x[0, 2, :, :, 3].all()  # unknown channel
    with torch.no_grad():
        y = model(x)
    assert y.shape == (1, 1, 16, 16, 8) and torch.isfinite(y).all()
    torch.manual_seed(0)
    with torch.no_grad():
        again = OccupancyNet().eval()(x)
        other = model(torch.from_numpy(encode(np.zeros_like(state), below=4))[None])
    torch.testing.assert_close(again, y, rtol=0, atol=0)  # seeded weights, same numbers
    assert not torch.allclose(other, y)  # and the output depends on what was seen


def test_shipped_model_continues_observed_ground_into_unseen_space():
    """The trained model on a window with flat ground seen on one half only."""
    ckpt = load_checkpoint()
    w = ckpt.window
    spec = GridSpec((0.0, 0.0, 0.0), w.voxel_m, w.size)
    grid = OccupancyGrid(spec)
    ground_k = w.below - 4  # the camera 1.6 m above the ground
    nx = w.size[0]
    grid.state[: nx // 2, :, ground_k] = OCCUPIED
    grid.state[: nx // 2, :, ground_k + 1:] = FREE
    predictor = OccupancyPredictor(ckpt, grid)
    camera = spec.centres(np.array([[nx // 2 - 1, w.size[1] // 2, w.below]]))[0]
    predictor.update(camera)
    p = predictor.probability.astype(np.float32)
    unseen_ground = p[nx // 2: nx // 2 + 8, 8:-8, ground_k]
    sky = p[nx // 2: nx // 2 + 8, 8:-8, ground_k + 8:]
    assert unseen_ground.mean() > 0.5, unseen_ground.mean()
    assert sky.max() < 0.5
    pts, prob = predictor.predicted()
    assert len(pts) == len(prob) > 0 and prob.min() >= 0.5
    assert np.all(pts[:, 0] >= (nx // 2) * w.voxel_m)  # nothing where a return already fell


def test_checkpoint_loads_offline_from_the_installed_package(tmp_path: Path):
    code = ("import json; from mapper.model import load_checkpoint, file_sha256, weights_sha256;"
            "c = load_checkpoint(); print(json.dumps([str(c.path), file_sha256(c.path), "
            "weights_sha256(c.model)]))")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                       text=True, timeout=120,
                       env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path),
                            "HTTPS_PROXY": "http://127.0.0.1:9", "HTTP_PROXY":
                            "http://127.0.0.1:9", "NO_PROXY": ""})
    assert r.returncode == 0, r.stderr
    path, sha, weights = json.loads(r.stdout)
    assert Path(path) == shipped_checkpoint()
    assert Path(path).stat().st_size <= 20e6
    summary = json.loads(Path(path).with_suffix(".json").read_text())
    assert summary["sha256"] == sha  # the summary describes this very file
    assert summary["weights_sha256"] == weights


def test_missing_or_corrupt_checkpoint_is_one_line_saying_how_to_rebuild(tmp_path: Path):
    with pytest.raises(CheckpointError, match=r"missing; rebuild it with `rovergate train --out "
                                         r".*nope\.pt`"):
        load_checkpoint(tmp_path / "nope.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match=r"corrupt .*rebuild it with `rovergate train --out "):
        load_checkpoint(junk)
    cut = tmp_path / "cut.pt"
    cut.write_bytes(shipped_checkpoint().read_bytes()[:5000])
    with pytest.raises(CheckpointError, match=r"corrupt") as e:
        load_checkpoint(cut)
    assert "\n" not in str(e.value)


@pytest.mark.e2e
def test_a_corrupt_checkpoint_stops_the_command_line_in_one_line(tmp_path: Path):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    r = subprocess.run([sys.executable, "-m", "mission.cli", "run", "--condition", "learned",
                        "--mapper.checkpoint", str(junk), "--out", str(tmp_path / "r")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        line for line in r.stderr.strip().splitlines() if "Traceback" not in line]
    assert r.stderr.strip().splitlines()[-1].startswith("error: the occupancy model checkpoint")
    assert not (tmp_path / "r" / "logs").exists(), "modules were started"


def test_training_writes_outside_the_package_unless_told_and_missions_load_the_shipped():
    """A trial `rovergate train` must not replace the shipped model; missions still use it."""
    import tyro

    from mapper.mapper import mission_checkpoint
    from rovergate.config import MissionConfig
    out = tyro.cli(TrainConfig, args=[]).out
    assert out == TrainConfig().out == Path("runs/train/occupancy.pt")
    package = shipped_checkpoint().resolve().parent.parent
    assert not out.resolve().is_relative_to(package)
    assert not out.with_suffix(".json").resolve().is_relative_to(package)
    assert mission_checkpoint(MissionConfig(condition="learned")).path == shipped_checkpoint()


def test_a_short_training_run_lowers_the_loss():
    cfg = TrainConfig(walk_steps=5, snapshot_every=2, iterations=40, batch=2, lr=4e-3,
                      crop=(32, 32, 32), threads=1, label_samples=100_000)
    window = WindowSpec()
    data = np.stack(gather_world((0, 1000, cfg, window)))
    assert data.shape[1:] == (2, *window.size)
    assert (data[:, 1] == 1).any() and (data[:, 0] & OCCUPIED).any()
    x, y = make_batch(data, np.arange(len(data)), window, window.size, None)
    torch.manual_seed(0)
    with torch.no_grad():
        before = float(masked_loss(OccupancyNet()(x), y, cfg.pos_weight))
    model, history = train(cfg, data, data[:0], window, progress=False)
    with torch.no_grad():
        after = float(masked_loss(model(x), y, cfg.pos_weight))
    assert after < 0.7 * before, (before, after)
    assert history["train_loss"] and history["iteration"][-1] == cfg.iterations


def test_data_and_training_are_deterministic():
    """What `rovergate train` relies on to reproduce the shipped weights."""
    cfg = TrainConfig(walk_steps=3, snapshot_every=2, iterations=3, batch=1,
                      crop=(16, 16, 16), threads=1, label_samples=50_000)
    window = WindowSpec()
    a = np.stack(gather_world((1, 1000, cfg, window)))
    b = np.stack(gather_world((1, 1000, cfg, window)))
    np.testing.assert_array_equal(a, b)
    m1, _ = train(cfg, a, a[:0], window, progress=False)
    m2, _ = train(cfg, a, a[:0], window, progress=False)
    for (k, v1), v2 in zip(m1.state_dict().items(), m2.state_dict().values(), strict=True):
        assert torch.equal(v1, v2), k


def test_heightmap_baseline_fills_unreached_columns_at_the_nearest_ground_height():
    spec = GridSpec((0.0, 0.0, 0.0), 1.0, (6, 3, 5))
    grid = OccupancyGrid(spec)
    grid.state[:3, :, 2] = OCCUPIED
    grid.state[:3, :, 3:] = FREE
    grid.state[3, 0, 2] = FREE  # a ray showed this one empty: no point there
    pts = heightmap_completion(grid, np.ones(spec.shape, dtype=bool))
    ijk, _ = spec.index(pts)
    assert set(map(tuple, ijk)) == {(i, j, 2) for i in range(3, 6) for j in range(3)} - {
        (3, 0, 2)}


def test_scores_count_hits_within_delta_by_region():
    spec = GridSpec((0.0, 0.0, 0.0), 1.0, (10, 1, 1))
    grid = OccupancyGrid(spec)
    grid.state[:5] = OCCUPIED  # x < 5 observed
    truth = np.array([[x + 0.5, 0.5, 0.5] for x in range(10)], dtype=np.float32)
    pred = np.array([[0.5, 0.5, 0.5], [6.5, 0.5, 0.5], [9.6, 0.5, 0.5], [7.0, 3.0, 0.5]],
                    dtype=np.float32)
    region = np.ones(spec.shape, dtype=bool)
    c = score_maps({"m": pred}, truth, cKDTree(truth), grid, region, (0, 0, 0, 10, 1, 1),
                   [0.2])
    obs, unobs = c[("m", 0, "observed")], c[("m", 0, "unobserved")]
    assert (obs.map_points, obs.map_hits, obs.truth_points, obs.truth_hits) == (1, 1, 5, 1)
    # (7, 3) is outside the box of interest; 6.5 hits, 9.6 is 0.1 from 9.5: hits.
    assert (unobs.map_points, unobs.map_hits, unobs.truth_points, unobs.truth_hits) == (
        2, 2, 5, 2)
    s = unobs.scores()
    assert s["precision"] == 1.0 and s["recall"] == 0.4
    assert Counts().scores()["precision"] is None


def test_prediction_is_published_as_a_surface_not_a_thick_band():
    """Ground one to three voxels thick is one point per column at its sub-voxel height; a
    wall keeps a point per voxel; a column whose surface was measured gets no point."""
    ckpt = load_checkpoint()
    spec = GridSpec((0.0, 0.0, 0.0), ckpt.window.voxel_m, (4, 1, 10))
    grid = OccupancyGrid(spec)
    predictor = OccupancyPredictor(ckpt, grid)
    p = predictor.probability
    p[0, 0, 2] = p[0, 0, 3] = 0.9  # ground between voxels 2 and 3: one point at their border
    p[1, 0, 2:5] = [0.6, 0.9, 0.6]  # unsure of its height, centred on voxel 3
    p[2, 0, 1:8] = 0.9  # a wall 2.8 m high
    p[3, 0, 4] = p[3, 0, 5] = 0.9
    grid.state[3, 0, 3] = OCCUPIED  # measured just under: S_t stands for this surface
    pts, prob = predictor.predicted()
    by_column = {i: sorted(z for (x, _, z) in pts.tolist() if int(x / spec.voxel_m) == i)
                 for i in range(4)}
    assert by_column[0] == pytest.approx([3.0 * spec.voxel_m])
    assert by_column[1] == pytest.approx([3.5 * spec.voxel_m])
    assert by_column[2] == pytest.approx([(k + 0.5) * spec.voxel_m for k in range(1, 8)])
    assert by_column[3] == []
    assert np.all(prob >= 0.5)


def test_free_space_is_the_rays_samples_up_to_a_voxel_short_of_each_return():
    """Every ray_stride-th return's ray, sampled every half voxel and stopping a voxel short of
    the return, marks its voxels free (the mask-and-nonzero formulation, written out here)."""
    rng = np.random.default_rng(5)
    spec = GridSpec((-12.0, -12.0, -6.0), 0.4, (60, 60, 30))
    k = CameraIntrinsics.from_fov(40, 30, 45.0)
    depth = rng.uniform(0.5, 14.0, (30, 40)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = np.nan
    T = _camera_looking_along_x(0.3, -0.2, 0.7)
    T[:3, :3] = T[:3, :3] @ np.array([[1, 0, 0], [0, np.cos(0.4), -np.sin(0.4)],
                                      [0, np.sin(0.4), np.cos(0.4)]])
    grid = OccupancyGrid(spec, ray_stride_px=2)
    grid.integrate(depth, k, T)
    sub = np.full_like(depth, np.nan)
    sub[::2, ::2] = depth[::2, ::2]
    hits = backproject(sub, k, T).astype(np.float64)
    d = hits - T[:3, 3]
    length = np.linalg.norm(d, axis=1)
    unit = d / np.maximum(length, 1e-9)[:, None]
    t = np.arange(int(np.ceil(length.max() / 0.2)) + 1) * 0.2
    rows, cols = np.nonzero(t[None, :] < (length - 0.4)[:, None])
    ijk, inside = spec.index(T[:3, 3] + unit[rows] * t[cols, None])
    expected = np.zeros(spec.shape, dtype=np.uint8).reshape(-1)
    expected[spec.flat(ijk[inside])] |= FREE
    ijk, inside = spec.index(backproject(depth, k, T))
    expected[spec.flat(ijk[inside])] |= OCCUPIED
    assert np.array_equal(grid.state.reshape(-1), expected)


def test_prediction_reads_thresholds_exactly_and_skips_an_unchanged_window():
    ckpt = load_checkpoint()
    w = ckpt.window
    spec = GridSpec((0.0, 0.0, 0.0), w.voxel_m, w.size)
    grid = OccupancyGrid(spec)
    predictor = OccupancyPredictor(ckpt, grid)
    p = np.random.default_rng(2).random(spec.shape).astype(np.float16)
    p.reshape(-1)[:6] = [0.0, 0.5, np.float16(0.5) - np.float16(2**-12), 1.0, 6e-8, 0.25]
    predictor.probability[:] = p
    for threshold in (0.5, 0.25, 0.3, 1.0, 0.0):
        assert np.array_equal(predictor._at_least(threshold), p >= threshold), threshold
    calls = []
    engine = predictor.engine
    predictor.engine = lambda state: calls.append(1) or engine(state)
    camera = spec.centres(np.array([[w.size[0] // 2, w.size[1] // 2, w.below]]))[0]
    predictor.update(camera)
    first = predictor.probability.copy()
    predictor.update(camera)  # the same window, the same grid: the same numbers, no model run
    assert len(calls) == 1 and np.array_equal(predictor.probability, first)
    grid.state[3, 3, 3] = OCCUPIED
    predictor.update(camera)
    assert len(calls) == 2


def test_probabilities_round_to_float16_as_numpy_rounds_them():
    """to_float16 at every float16 number in [0, 1], at every rounding boundary between two
    of them (a tie: to even) and a few float32 steps either side, and at random."""
    from mapper.predictor import to_float16
    half = np.arange(0, 0x3C01, dtype=np.uint16).view(np.float16).astype(np.float32)
    mid = ((half[:-1].astype(np.float64) + half[1:]) / 2).astype(np.float32)  # exact
    values = [half, mid]
    for direction in (np.float32(2.0), np.float32(-1.0)):
        x = mid
        for _ in range(3):
            x = np.nextafter(x, direction, dtype=np.float32)
            values.append(x)
    values.append(np.random.default_rng(4).random(1_000_000, dtype=np.float32))
    v = np.concatenate(values)
    assert np.array_equal(to_float16(v).view(np.uint16), v.astype(np.float16).view(np.uint16))


def _ground_window(w: WindowSpec, seed: int = 0) -> np.ndarray:
    """A state window as a mission makes one: ground under the camera seen over half the
    window, free space above it, a few scattered returns, unknown elsewhere."""
    state = np.zeros(w.size, dtype=np.uint8)
    state[: w.size[0] // 2, :, w.below - 4] = OCCUPIED
    state[: w.size[0] // 2, :, w.below - 3:] = FREE
    rng = np.random.default_rng(seed)
    ijk = rng.integers(0, w.size, size=(300, 3))
    state[tuple(ijk.T)] |= OCCUPIED
    return state


def test_the_openvino_engine_computes_the_trained_network():
    """The default engine (its stem folded over the constant channels, its head folded into the
    last up-convolution) gives the torch network's float32 logits to the sums' rounding, on a
    window as missions see them and on one with nothing in it."""
    from mapper.engines import make_engine
    ckpt = load_checkpoint()
    fast, trained = make_engine(ckpt, "openvino"), make_engine(ckpt, "torch")
    for state in (_ground_window(ckpt.window), np.zeros(ckpt.window.size, np.uint8)):
        a, b = fast(state), trained(state)
        assert a.shape == b.shape == ckpt.window.size and a.dtype == np.float32
        assert np.abs(a - b).max() < 1e-3, np.abs(a - b).max()
        assert np.mean((a >= 0) != (b >= 0)) < 1e-5


def test_the_openvino_engine_gives_the_same_logits_with_any_number_of_threads():
    from mapper.engines import make_engine
    ckpt = load_checkpoint()
    state = _ground_window(ckpt.window, seed=1)
    before = torch.get_num_threads()
    out = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            engine = make_engine(ckpt, "openvino")
            out += [engine(state), engine(state)]
    finally:
        torch.set_num_threads(before)
    assert all(np.array_equal(out[0], o) for o in out[1:])


_LOGITS_DIGEST = """
import hashlib, numpy as np, torch
from mapper.engines import make_engine
from mapper.model import load_checkpoint
torch.set_num_threads(1)
ckpt = load_checkpoint()
state = np.random.default_rng(3).choice(np.array([0, 1, 2], np.uint8), ckpt.window.size,
                                        p=[0.7, 0.1, 0.2])
engine = make_engine(ckpt, "openvino")
print(torch.backends.cpu.get_cpu_capability(), any("avx512" in k for k in engine.kernels()),
      hashlib.sha256(engine(state).tobytes()).hexdigest())
"""


def test_the_openvino_engine_gives_the_same_logits_with_the_instruction_set_capped_at_avx2():
    """The README's cross-CPU claim: the default engine's logits do not depend on the vector
    instructions oneDNN uses (its AVX2 or AVX-512 kernels; on an AVX2-only CPU both runs are
    AVX2, and the test checks only that they agree)."""
    digests = {}
    for capped in (True, False):
        env = {k: v for k, v in os.environ.items()
               if k not in ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY")}
        if capped:
            env.update(ONEDNN_MAX_CPU_ISA="AVX2", ATEN_CPU_CAPABILITY="avx2")
        out = subprocess.run([sys.executable, "-c", _LOGITS_DIGEST], env=env, text=True,
                             capture_output=True, timeout=120)
        assert out.returncode == 0, out.stderr[-2000:]
        digests[capped] = out.stdout.split()
    # Capped, neither ATen nor oneDNN (OpenVINO's kernels) uses AVX-512; uncapped on a CPU
    # that has it, oneDNN does, so the two runs really took different kernels.
    assert digests[True][:2] == ["AVX2", "False"], digests
    if digests[False][0].startswith("AVX512"):
        assert digests[False][1] == "True", digests
    assert digests[True][2] == digests[False][2], digests


def test_the_model_in_bfloat16_predicts_nearly_what_it_does_in_float32():
    ckpt = load_checkpoint()
    w = ckpt.window
    spec = GridSpec((0.0, 0.0, 0.0), w.voxel_m, w.size)
    grid = OccupancyGrid(spec)
    grid.state[:] = _ground_window(w)
    camera = spec.centres(np.array([[w.size[0] // 2 - 1, w.size[1] // 2, w.below]]))[0]
    full = OccupancyPredictor(ckpt, grid)
    full.update(camera)
    a = full.probability.astype(np.float32)
    halves = [OccupancyPredictor(ckpt, grid, "bfloat16", "torch")]
    try:
        halves.append(OccupancyPredictor(ckpt, grid, "bfloat16", "openvino"))
    except ConfigError as e:  # a CPU without native bfloat16 (or with it capped, as in CI)
        assert "native bfloat16" in str(e) and "--mapper.precision float32" in str(e)
    for half in halves:
        half.update(camera)
        b = half.probability.astype(np.float32)
        assert np.abs(a - b).max() < 0.05 and np.mean((a >= 0.5) != (b >= 0.5)) < 1e-3
    assert ckpt.model.stem[0].weight.dtype == torch.float32  # the checkpoint's is untouched


def test_an_unknown_engine_or_precision_is_refused_with_the_choices():
    ckpt = load_checkpoint()
    grid = OccupancyGrid(GridSpec((0.0, 0.0, 0.0), ckpt.window.voxel_m, ckpt.window.size))
    with pytest.raises(ConfigError, match="float32, bfloat16"):
        OccupancyPredictor(ckpt, grid, "float16")
    with pytest.raises(ConfigError, match="openvino, torch"):
        OccupancyPredictor(ckpt, grid, "float32", "onnx")
