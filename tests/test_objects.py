"""The built-in object set: BOP models folder, sizes, determinism, symmetries that hold when rendered."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sc6d_jax import bop
from sc6d_jax.objects import ASYMMETRIC_IDS, SYMMETRIC_IDS, builtin_objects, write_models
from sc6d_jax.objects.cli import main



def test_models_folder_is_bop(models):
    infos = bop.load_models_info(models)
    assert len(infos) >= 12 and sorted(infos) == list(range(1, len(infos) + 1))
    kinds = {"continuous": 0, "discrete": 0, "none": 0}
    for obj_id, info in infos.items():
        pts = bop.load_model_points(models, obj_id)
        ext = pts.max(0) - pts.min(0)
        assert 40.0 <= ext.max() <= 200.0, (obj_id, ext)  # 4-20 cm, in mm
        np.testing.assert_allclose(info.size_xyz, ext, rtol=1e-5)
        d = np.linalg.norm(pts[:, None] - pts[None], axis=-1).max() if len(pts) < 3000 else None
        if d is not None:
            assert info.diameter == pytest.approx(d, rel=1e-5)
        kinds["continuous" if info.symmetries_continuous else "discrete" if info.symmetries_discrete else "none"] += 1
    assert kinds["continuous"] >= 3 and kinds["discrete"] >= 3 and kinds["none"] >= 3
    assert set(SYMMETRIC_IDS).isdisjoint(ASYMMETRIC_IDS)


def test_same_seed_same_bytes_other_seed_differs(tmp_path, models):
    write_models(tmp_path / "a")
    write_models(tmp_path / "b", seed=1)
    for p in sorted(models.iterdir()):
        assert (tmp_path / "a" / p.name).read_bytes() == p.read_bytes()
    assert (tmp_path / "b" / "obj_000002.ply").read_bytes() != (models / "obj_000002.ply").read_bytes()


def test_symmetries_are_exact_on_vertices():
    for o in builtin_objects():
        v = o.mesh.vertices
        for S in o.symmetries_discrete:
            w = v @ S[:3, :3].T + S[:3, 3]
            # every transformed vertex lies on the surface: nearest vertex distance ~0 for our meshes
            d = np.min(np.linalg.norm(w[:, None] - v[None], axis=-1), axis=1)
            assert d.max() < 1e-6, (o.name, d.max())


def test_symmetric_poses_render_the_same_image(models):
    from sc6d_jax.render import Renderer, load_mesh

    infos = bop.load_models_info(models)
    ids = [i for i in SYMMETRIC_IDS]
    meshes = {i: load_mesh(bop.model_path(models, i)) for i in ids}
    K = np.array([[500.0, 0, 63.5], [0, 500.0, 63.5], [0, 0, 1]])
    t = np.array([0.0, 0.0, 900.0])
    with Renderer(meshes, 128, 128) as r:
        for i in ids:
            R = Rotation.random(random_state=i).as_matrix()
            a = r.render([(i, R, t)], K).rgb.astype(int)
            syms = [S[:3, :3] for S in infos[i].symmetries_discrete]
            for c in infos[i].symmetries_continuous:
                syms.append(Rotation.from_rotvec(np.asarray(c["axis"]) * 1.1).as_matrix())
            for S in syms:
                b = r.render([(i, R @ S, t)], K).rgb.astype(int)
                assert np.mean(np.abs(a - b).max(-1) > 40) < 0.003, (i, S)
        # control: an asymmetric object does change under a 180-degree turn
    meshes = {1: load_mesh(bop.model_path(models, 1))}
    with Renderer(meshes, 128, 128) as r:
        R = Rotation.random(random_state=0).as_matrix()
        a = r.render([(1, R, t)], K).rgb.astype(int)
        b = r.render([(1, R @ Rotation.from_euler("z", 180, degrees=True).as_matrix(), t)], K).rgb.astype(int)
        assert np.mean(np.abs(a - b).max(-1) > 40) > 0.01


def test_cli(tmp_path, capsys):
    assert main(["--out", str(tmp_path / "m")]) == 0
    assert "cylinder" in capsys.readouterr().out
    with pytest.raises(FileExistsError):
        main(["--out", str(tmp_path / "m")])
    assert main(["--out", str(tmp_path / "m"), "--overwrite"]) == 0
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left
