"""Benchmark: training crops per second, MuJoCo (this project) vs pyrender on the same scenes.

    python experiments/bench_render.py [--crops 256] [--repeats 3] [--sizes 64,128,256]

For each crop size and 1 / 2 worker processes it prints:
- ``mujoco`` and ``pyrender``: crops/s rendering the SAME scenes (target object + up to two
  occluding objects, each crop through its own K_B) with RGB + depth + per-instance masks;
- ``stream``: crops/s of the full training stream (sc6d_jax.data.CropStream: scene sampling,
  rendering, backgrounds, augmentation, labels, PE maps).
Figures are medians over repeats, measured in the same run. pyrender is optional
(``pip install pyrender && pip install -U "pyopengl>=3.1.7"``: pyrender pins an old PyOpenGL that breaks MuJoCo's EGL); its columns are skipped with a message when it is missing.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def make_scenes(models_dir: Path, size: int, n: int, seed: int = 0) -> list:
    from scipy.spatial.transform import Rotation

    from sc6d_jax import geometry as G
    from sc6d_jax.bop import load_models_info, model_path
    from sc6d_jax.data import sample_pose
    from sc6d_jax.render import load_mesh

    infos = load_models_info(models_dir)
    ids = sorted(infos)
    verts = {i: np.asarray(load_mesh(model_path(models_dir, i)).vertices) for i in ids}
    diam = {i: infos[i].diameter for i in ids}
    rng = np.random.default_rng(seed)
    scenes = []
    for _ in range(n):
        p = sample_pose(rng, ids, verts, diam)
        c = np.array([p.box[0] + p.box[2] / 2, p.box[1] + p.box[3] / 2])
        side = 1.5 * max(p.box[2], p.box[3])
        K_B = np.asarray(G.crop_transform(c, side, size), np.float64) @ p.K
        objs = [(p.obj_id, p.R, p.t)]
        for _ in range(rng.integers(0, 3)):
            oid = int(rng.choice([i for i in ids if i != p.obj_id]))
            if any(o[0] == oid for o in objs):
                continue
            d = p.t[2] * rng.uniform(0.6, 0.9)
            off = rng.uniform(-0.4, 0.4, 2) * side / p.K[0, 0] * d
            objs.append((oid, Rotation.random(random_state=rng).as_matrix(), p.t * d / p.t[2] + [off[0], off[1], 0]))
        scenes.append((objs, K_B))
    return scenes


class _MujocoBackend:
    def __init__(self, models_dir, size):
        from sc6d_jax.bop import load_models_info, model_path
        from sc6d_jax.render import Renderer, load_mesh

        ids = sorted(load_models_info(models_dir))
        self.r = Renderer({i: load_mesh(model_path(models_dir, i)) for i in ids}, size, size)

    def render(self, objs, K):
        out = self.r.render(objs, K)
        return out.rgb, out.depth, out.instance


class _PyrenderBackend:
    """pyrender with the same meshes: colour + depth pass, then a segmentation pass."""

    def __init__(self, models_dir, size):
        import pyrender

        from sc6d_jax.bop import load_models_info, model_path
        from sc6d_jax.render import load_mesh

        self.pr = pyrender
        self.scene = pyrender.Scene(ambient_light=[0.3, 0.3, 0.3], bg_color=[0, 0, 0, 0])
        self.nodes = {}
        for i in sorted(load_models_info(models_dir)):
            m = pyrender.Mesh.from_trimesh(load_mesh(model_path(models_dir, i)), smooth=False)
            node = self.scene.add(m, pose=np.eye(4))
            node.mesh.is_visible = False
            self.nodes[i] = node
        self.scene.add(pyrender.DirectionalLight(intensity=3.0), pose=np.eye(4))
        self.cam = pyrender.IntrinsicsCamera(1, 1, 0, 0, znear=10.0, zfar=20000.0)
        self.cam_node = self.scene.add(self.cam, pose=np.diag([1.0, -1.0, -1.0, 1.0]))  # OpenCV -> OpenGL
        self.r = pyrender.OffscreenRenderer(size, size)
        self.seg_colors = {}

    def render(self, objs, K):
        pr = self.pr
        for node in self.nodes.values():
            node.mesh.is_visible = False
        seg = {}
        for k, (oid, R, t) in enumerate(objs):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t
            node = self.nodes[oid]
            self.scene.set_pose(node, T)
            node.mesh.is_visible = True
            seg[node] = (k + 1, 0, 0)
        self.cam.fx, self.cam.fy, self.cam.cx, self.cam.cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        rgb, depth = self.r.render(self.scene)
        inst, _ = self.r.render(self.scene, flags=pr.RenderFlags.SEG, seg_node_map=seg)
        return rgb, depth, inst[..., 0].astype(np.int32) - 1


_B = None


def _init(backend, models_dir, size):
    global _B
    os.environ["LP_NUM_THREADS"] = "1"
    _B = (_MujocoBackend if backend == "mujoco" else _PyrenderBackend)(models_dir, size)


def _run(scenes):
    for objs, K in scenes:
        _B.render(objs, K)
    return len(scenes)


def time_backend(backend, models_dir, size, scenes, workers, repeats):
    ctx = mp.get_context("spawn")
    with cf.ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init, initargs=(backend, str(models_dir), size)) as ex:
        chunks = [scenes[i::workers] for i in range(workers)]
        list(ex.map(_run, [c[:4] for c in chunks]))  # warm up every worker
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            n = sum(ex.map(_run, chunks))
            times.append(n / (time.perf_counter() - t0))
    return statistics.median(times)


def time_stream(models_dir, size, workers, n, repeats):
    from sc6d_jax.data import CropStream, StreamConfig

    bs = 32
    with CropStream(StreamConfig(str(models_dir), crop_size=size, batch_size=bs, workers=workers)) as s:
        next(s)
        rates = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            for _ in range(max(n // bs, 1)):
                next(s)
            rates.append(max(n // bs, 1) * bs / (time.perf_counter() - t0))
    return statistics.median(rates)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--crops", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sizes", default="64,128,256")
    a = ap.parse_args()
    from sc6d_jax.objects import write_models

    try:
        import pyrender  # noqa: F401

        have_pyrender = True
    except Exception as exc:  # pragma: no cover - optional
        have_pyrender = False
        print(f"pyrender not available ({exc}); its columns are skipped", file=sys.stderr)
    with tempfile.TemporaryDirectory() as tmp:
        models = write_models(Path(tmp) / "models")
        print(f"{'size':>5} {'workers':>7} {'mujoco/s':>9} {'pyrender/s':>10} {'ratio':>6} {'stream/s':>9}")
        for size in [int(s) for s in a.sizes.split(",")]:
            scenes = make_scenes(models, size, a.crops)
            for w in (1, 2):
                mj = time_backend("mujoco", models, size, scenes, w, a.repeats)
                pr = time_backend("pyrender", models, size, scenes, w, a.repeats) if have_pyrender else float("nan")
                st = time_stream(models, size, w, a.crops, a.repeats)
                print(f"{size:>5} {w:>7} {mj:>9.0f} {pr:>10.0f} {mj / pr:>6.2f} {st:>9.0f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
