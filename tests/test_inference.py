"""Estimator: predict shapes and types, no recompilation, TTA / refinement, bad input, export,
the library cache, the TTA rotation convention and the ``sc6d predict`` CLI."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sc6d_jax import Estimator
from sc6d_jax.geometry import crop_transform, warp_crop
from sc6d_jax.inference import load_exported, load_or_build_library, predict_crops, rotate_crops, rz90
from sc6d_jax.inference._library import library_key

OBJ_IDS = (1, 2, 3)
LIB = 480  # 4 views x 120 in-plane rotations: small, so the tests compile and run fast


def _is_rotation(R, atol=1e-4):
    R = np.asarray(R, np.float64)
    eye = np.broadcast_to(np.eye(3), R.shape)
    return np.allclose(R @ np.swapaxes(R, -1, -2), eye, atol=atol) and np.allclose(np.linalg.det(R), 1.0, atol=atol)


@pytest.fixture(scope="session")
def run_dir(tmp_path_factory):
    """A run directory holding one checkpoint of a freshly initialised tiny model (3 objects)."""
    from sc6d_jax.model import init
    from sc6d_jax.train import StreamSettings, preset, save_checkpoint

    cfg = preset("tiny")
    cfg = cfg.replace(
        model=dataclasses.replace(cfg.model, n_objects=len(OBJ_IDS)),
        stream=StreamSettings(batch_size=16, obj_ids=OBJ_IDS),
        z_range=(20.0, 400.0),
    )
    params = init(jax.random.PRNGKey(0), cfg.model)
    d = tmp_path_factory.mktemp("run")
    save_checkpoint(d, 1, params, {}, np.zeros(2, np.uint32), cfg.to_dict(), extra_meta={"models_dir": None})
    return d


@pytest.fixture(scope="session")
def est(run_dir):
    return Estimator.load(run_dir, library_size=LIB, progress=False)


@pytest.fixture(scope="session")
def scene():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)
    K = np.array([[120.0, 0, 64], [0, 120.0, 48], [0, 0, 1]])
    boxes = np.array([[10, 10, 30, 40], [50, 20, 20, 20], [0, 0, 100, 90]], float)
    return image, K, boxes, [1, 3, 3]


def test_predict_types_and_no_recompilation(est, scene):
    image, K, boxes, ids = scene
    out = est.predict(image, K, boxes, ids, top_k=3)
    assert len(out) == 3
    for p, oid in zip(out, ids):
        assert p.obj_id == oid
        assert p.R.shape == (3, 3) and p.t.shape == (3,) and p.R_topk.shape == (3, 3, 3)
        assert p.prob_topk.shape == (3,) and p.score_topk.shape == (3,)
        assert _is_rotation(p.R) and _is_rotation(p.R_topk)
        assert np.all(np.isfinite(p.t)) and p.t[2] > 0
        assert -1.0 - 1e-5 <= p.score <= 1.0 + 1e-5 and 0.0 < p.prob <= 1.0
        assert np.all(np.diff(p.score_topk) <= 1e-6)
        np.testing.assert_allclose(p.R, p.R_topk[0])
    n0 = predict_crops._cache_size()
    # same bucket (4 boxes) with other boxes and objects: no new compilation
    out2 = est.predict(image, K, boxes[::-1] + 1, [2, 2, 1], top_k=3)
    assert predict_crops._cache_size() == n0
    assert len(out2) == 3
    # the same crop alone gives the same pose as in a batch (padding does not leak)
    single = est.predict(image, K, boxes[:1], ids[:1], top_k=3)[0]
    np.testing.assert_allclose(single.R, out[0].R, atol=1e-4)
    np.testing.assert_allclose(single.t, out[0].t, rtol=1e-4)


def test_grayscale_and_empty(est, scene):
    image, K, boxes, ids = scene
    assert est.predict(image, K, np.zeros((0, 4)), []) == []
    gray = image[:, :, 0]
    a = est.predict(gray, K, boxes[:1], ids[:1])[0]
    b = est.predict(np.repeat(gray[:, :, None], 3, axis=2), K, boxes[:1], ids[:1])[0]
    np.testing.assert_allclose(a.R, b.R)


def test_tta_and_refine_return_valid_rotations(est, scene):
    image, K, boxes, ids = scene
    plain = est.predict(image, K, boxes, ids)
    out = est.predict(image, K, boxes, ids, tta=True, refine=True, tta_mode="best")
    for p, q in zip(out, plain):
        assert _is_rotation(p.R, atol=1e-3) and np.all(np.isfinite(p.t)) and p.t[2] > 0
        assert p.score >= -1.0
    # refinement never lowers the cosine of the copy it starts from (TTA's best copy >= copy 0)
    assert all(p.score >= q.score - 1e-5 for p, q in zip(out, plain))
    with pytest.raises(ValueError, match="tta_mode"):
        est.predict(image, K, boxes, ids, tta=True, tta_mode="vote")


def test_fused_tta_picks_the_candidate_all_four_copies_score_best(est, scene):
    """tta_mode="fuse": the rotation (allocentric, in the crop's frame) maximises the four copies'
    mean cosine mean_k <f_k, g(Rz(90k) R)> over the pooled candidates, so it scores at least as
    high on that mean as the authors' pick (the best single copy's top-1, which is among the
    candidates); score is that mean, prob the copies' mean library probability; translation is
    the same in both modes; refinement does not lower the mean."""
    from sc6d_jax.geometry import crop_transform, pe_map
    from sc6d_jax.model import apply, encode_rotations

    image, K, boxes, ids = scene
    n_pad = 4
    crops, center, side = est.make_crops(image, boxes, n_pad)
    obj = np.concatenate([est.obj_index(ids), est.obj_index(ids[:1])])
    Kb = np.broadcast_to(K.astype(np.float32), (n_pad, 3, 3))
    fuse = est.predict_crops(crops, Kb, center, side, obj, tta=True, top_k=3)
    best = est.predict_crops(crops, Kb, center, side, obj, tta=True, top_k=3, tta_mode="best")
    refined = est.predict_crops(crops, Kb, center, side, obj, tta=True, top_k=3, refine=True)

    pe = pe_map(jnp.asarray(Kb), crop_transform(jnp.asarray(center), jnp.asarray(side), est.mcfg.crop_size),
                est.mcfg.crop_size)
    f = [apply(est.params, est.mcfg, rotate_crops(jnp.asarray(crops), k), pe if est.mcfg.use_pe else None,
               jnp.asarray(obj))["rot_emb"] for k in range(4)]

    def mean_cos(R_allo):  # (B,3,3) -> (B,)
        g = [encode_rotations(est.params, est.mcfg, rz90(k) @ jnp.asarray(R_allo), jnp.asarray(obj)) for k in range(4)]
        return np.asarray(sum(jnp.sum(gk * fk, axis=-1) for gk, fk in zip(g, f)) / 4)

    np.testing.assert_allclose(fuse["score"], mean_cos(fuse["R_allo"]), atol=1e-4)
    assert np.all(fuse["score"] >= mean_cos(best["R_allo"]) - 1e-4)
    assert np.all(np.diff(fuse["score_topk"], axis=1) <= 1e-6) and np.all((fuse["prob"] > 0) & (fuse["prob"] <= 1))
    np.testing.assert_allclose(fuse["t"], best["t"], rtol=1e-5)
    assert np.all(refined["score"] >= fuse["score"] - 1e-5)
    np.testing.assert_allclose(refined["score"], mean_cos(refined["R_allo"]), atol=1e-4)


def test_crops_are_cut_with_the_models_crop_pad(est, scene):
    """The estimator cuts each crop ``mcfg.crop_pad * max(w, h)`` wide around the box centre,
    as the model's training stream did (``model.crop_pad``; 1.5 by default)."""
    import copy

    image, K, boxes, ids = scene
    _, center, side = est.make_crops(image, boxes, len(boxes))
    np.testing.assert_allclose(side, 1.5 * boxes[:, 2:].max(axis=1), rtol=1e-5)
    tight = copy.copy(est)
    tight.mcfg = dataclasses.replace(est.mcfg, crop_pad=1.2)
    crops2, center2, side2 = tight.make_crops(image, boxes, len(boxes))
    np.testing.assert_allclose(side2, 1.2 * boxes[:, 2:].max(axis=1), rtol=1e-5)
    np.testing.assert_allclose(center2, center)
    assert crops2.shape[1] == est.mcfg.crop_size
    # model.crop_supersample: each crop pixel the mean of f x f samples, as the stream rendered them
    crops1, _, _ = est.make_crops(image, boxes, len(boxes))
    fine = copy.copy(est)
    fine.mcfg = dataclasses.replace(est.mcfg, crop_supersample=4)
    crops4, center4, side4 = fine.make_crops(image, boxes, len(boxes))
    T = np.asarray(crop_transform(center4, side4, est.mcfg.crop_size))
    np.testing.assert_array_equal(crops4, warp_crop(image, T, est.mcfg.crop_size, supersample=4))
    assert crops4.shape == crops1.shape and np.any(crops4 != crops1)


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(image=np.zeros((96, 128, 3), np.float32)), "uint8"),
        (dict(image=np.zeros((96, 128, 4), np.uint8)), "HxWx3"),
        (dict(K=np.eye(4)), "3x3"),
        (dict(K=np.array([[np.nan, 0, 1], [0, 1, 1], [0, 0, 1]])), "NaN|finite"),
        (dict(boxes=np.array([[10, 10, 0, 5.0]])), "positive width"),
        (dict(boxes=np.array([[500, 10, 5, 5.0]])), "outside"),
        (dict(boxes=np.array([[np.nan, 10, 5, 5.0]])), "NaN|finite"),
        (dict(boxes=np.array([10, 10, 5, 5.0])), "N x 4"),
        (dict(obj_ids=[7]), "unknown object"),
        (dict(obj_ids=[1, 2]), "obj_ids"),
    ],
)
def test_bad_input_raises_before_compiling(est, scene, change, match):
    image, K, boxes, ids = scene
    kw = dict(image=image, K=K, boxes=boxes[:1], obj_ids=ids[:1])
    kw.update(change)
    n0 = predict_crops._cache_size()
    with pytest.raises(ValueError, match=match):
        est.predict(**kw)
    assert predict_crops._cache_size() == n0


def test_export_round_trip(est, scene, tmp_path):
    image, K, boxes, ids = scene
    path = est.export(tmp_path / "predictor.npz")
    f = load_exported(path)
    assert f.meta["obj_ids"] == list(OBJ_IDS) and f.meta["crop_pad"] == est.mcfg.crop_pad and f.meta["crop_supersample"] == 1
    crops, center, side = est.make_crops(image, boxes, len(boxes))
    idx = est.obj_index(ids)
    Kb = np.broadcast_to(K, (len(boxes), 3, 3))
    got = f(crops, Kb, center, side, idx)
    ref = est.predict_crops(crops, Kb, center, side, idx)
    np.testing.assert_allclose(got["R"], ref["R"], atol=1e-5)
    np.testing.assert_allclose(got["t"], ref["t"], rtol=1e-5)
    with pytest.raises(ValueError, match="uint8"):
        f(crops.astype(np.float32), Kb, center, side, idx)
    # fused TTA exports too (the four copies and the pooled candidates inside the one function)
    f4 = load_exported(est.export(tmp_path / "predictor_tta.npz", tta=True))
    assert f4.meta["tta"] is True and f4.meta["tta_mode"] == "fuse"
    got, ref = f4(crops, Kb, center, side, idx), est.predict_crops(crops, Kb, center, side, idx, tta=True)
    np.testing.assert_allclose(got["R"], ref["R"], atol=1e-5)
    np.testing.assert_allclose(got["score"], ref["score"], atol=1e-5)


def test_library_cache_and_key(run_dir, est):
    files = list((run_dir / "library").glob("so3lib_*.npz"))
    assert len(files) == 1 and est.library.key in files[0].name
    lib2 = load_or_build_library(est.params, est.mcfg, LIB, cache_dir=run_dir / "library", progress=False)
    np.testing.assert_array_equal(lib2.emb, est.library.emb)
    # embeddings are unit vectors of the model's SO(3) encoder
    from sc6d_jax.model import encode_rotations

    e = encode_rotations(est.params, est.mcfg, jnp.asarray(est.library.R[:5]), 2)
    np.testing.assert_allclose(est.library.emb[2, :5], np.asarray(e), atol=1e-6)
    # another model or another grid -> another key
    p2 = jax.tree.map(lambda a: a, est.params)
    p2["rot_head"] = jax.tree.map(lambda a: a + 1e-3, p2["rot_head"])
    assert library_key(p2, est.mcfg, est.library.grid) != est.library.key
    assert library_key(est.params, est.mcfg, (4, 121, 0)) != est.library.key


def test_tta_rotation_matches_rz90():
    """Turning the object by Rz(90 k) about the optical axis = rotate_crops(crop, k)."""
    S, f = 33, 40.0
    c = (S - 1) / 2
    K = np.array([[f, 0, c], [0, f, c], [0, 0, 1]])
    pts = np.random.default_rng(1).normal(size=(40, 3)) * 8
    t = np.array([0, 0, 100.0])

    def render(R):
        img = np.zeros((S, S, 1), np.float32)
        uv = (pts @ R.T + t) @ K.T
        uv = np.round(uv[:, :2] / uv[:, 2:3]).astype(int)
        img[uv[:, 1], uv[:, 0], 0] = 1
        return img

    from scipy.spatial.transform import Rotation

    R0 = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    for k in range(4):
        a = np.asarray(rotate_crops(jnp.asarray(render(R0))[None], k))[0]
        b = render(np.asarray(rz90(k)) @ R0)
        np.testing.assert_array_equal(a, b)


def test_predict_cli_on_bop_dataset(run_dir, shared_data, tmp_path, capsys, monkeypatch):
    from sc6d_jax.bop import BopDataset, bbox_extent, read_results_csv
    from sc6d_jax.inference import _estimator
    from sc6d_jax.inference.cli import main as predict_main
    from sc6d_jax.metrics.cli import main as eval_main

    ds = shared_data / "bop_reference" / "tudl"
    out = tmp_path / "sc6d_tudl-test.csv"
    seen = []  # the boxes each image's call gets: the extents of the ground truth's bbox_visib
    real_predict = _estimator.Estimator.predict
    monkeypatch.setattr(_estimator.Estimator, "predict",
                        lambda self, image, K, boxes, *a, **k: seen.append(np.array(boxes)) or real_predict(self, image, K, boxes, *a, **k))
    # the library was cached by the session's Estimator: same size -> no rebuild
    assert predict_main(["--run", str(run_dir), "--dataset", str(ds), "--out", str(out),
                         "--library-size", "480", "--no-progress"]) == 0
    bop = BopDataset(ds)
    first = min(bop.targets(), key=lambda t: (t.scene_id, t.im_id))
    gti = [gi for g, gi in zip(bop.scene_gt(first.scene_id)[first.im_id], bop.scene_gt_info(first.scene_id)[first.im_id])
           if g.obj_id == first.obj_id]
    np.testing.assert_allclose(seen[0][0], bbox_extent(max(gti, key=lambda gi: gi.px_count_visib).bbox_visib))
    est = read_results_csv(out)
    assert len(est) > 0 and all(np.isfinite(e.t).all() and _is_rotation(e.R, 1e-3) for e in est)
    per_image = {}
    for e in est:
        per_image.setdefault((e.scene_id, e.im_id), set()).add(e.time)
    assert all(len(v) == 1 for v in per_image.values())
    scores = tmp_path / "scores.json"
    assert eval_main(["--dataset", str(ds), "--results", str(out), "--out", str(scores), "--no-vsd",
                      "--no-progress"]) == 0
    s = json.loads(scores.read_text())
    assert any("mssd" in k.lower() for k in s)


def test_predict_cli_image_mode(run_dir, scene, tmp_path, capsys):
    import cv2

    from sc6d_jax.inference.cli import main as predict_main

    image, K, boxes, ids = scene
    cv2.imwrite(str(tmp_path / "im.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    (tmp_path / "K.json").write_text(json.dumps({"cam_K": K.reshape(-1).tolist()}))
    (tmp_path / "boxes.json").write_text(json.dumps(boxes.tolist()))
    rc = predict_main(["--run", str(run_dir), "--image", str(tmp_path / "im.png"), "--camera", str(tmp_path / "K.json"),
                       "--boxes", str(tmp_path / "boxes.json"), "--obj-ids", "1,3,3", "--library-size", "480",
                       "--overlay", str(tmp_path / "ov.png"), "--no-progress"])
    assert rc == 0
    poses = json.loads(capsys.readouterr().out)["poses"]
    assert [p["obj_id"] for p in poses] == ids
    assert (tmp_path / "ov.png").is_file()
    with pytest.raises(ValueError, match="obj-ids"):
        predict_main(["--run", str(run_dir), "--image", str(tmp_path / "im.png"), "--camera", str(tmp_path / "K.json"),
                      "--boxes", str(tmp_path / "boxes.json"), "--obj-ids", "1", "--library-size", "480"])


def test_shipped_model_by_name(run_dir, est, scene, tmp_path, monkeypatch):
    """A run shipped as a named model loads by name, predicts the same poses, and caches its
    library in the user cache (never inside the package)."""
    from sc6d_jax import pretrained

    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "pretrained")
    monkeypatch.setenv("SC6D_CACHE", str(tmp_path / "cache"))
    shipped = pretrained.ship(run_dir, tmp_path / "pretrained" / "builtin", note="test")
    assert pretrained.available() == ["builtin"]
    assert sorted(p.name for p in shipped.iterdir()) == ["meta.json", "state.npz"]
    named = Estimator.load("builtin", library_size=LIB, progress=False)
    image, K, boxes, ids = scene
    a, b = est.predict(image, K, boxes, ids), named.predict(image, K, boxes, ids)
    for pa, pb in zip(a, b):
        np.testing.assert_allclose(pa.R, pb.R, atol=1e-5)
        np.testing.assert_allclose(pa.t, pb.t, rtol=1e-5)
    assert list((tmp_path / "cache").glob("builtin-*/library/so3lib_*.npz"))
    assert sorted(p.name for p in shipped.iterdir()) == ["meta.json", "state.npz"]
    with pytest.raises(FileNotFoundError, match="no shipped model 'lmo'.*shipped: builtin"):
        Estimator.load("lmo", library_size=LIB, progress=False)
    # a path is still a path, even when a folder of that name exists here
    monkeypatch.chdir(tmp_path)
    (tmp_path / "lmo").mkdir()
    assert pretrained.resolve("lmo") == (Path("lmo"), Path("lmo") / "library")


# ----------------------------------------------------------------------------- Implicit-PDF head


def test_ipdf_matching_equals_the_heads_dense_scores(monkeypatch):
    """Chunked scoring of an Implicit-PDF head over a padded library = the head's own logits
    (``rotation_logits``) over all rotations: the same top-k rows, scores and softmax."""
    import sc6d_jax.inference._matching as matching
    from sc6d_jax.geometry import random_rotations
    from sc6d_jax.inference import ipdf_match_blocks, pad_library
    from sc6d_jax.model import ModelConfig, init, rotation_features, rotation_logits

    cfg = ModelConfig(n_objects=3, crop_size=32, backbone="tiny", width=8, decoder_width=16, feat_dim=8, emb_dim=8,
                      n_z_bins=16, pose_width=8, head_hidden=16, so3_hidden=16, ipdf_hidden=16, gn_groups=4,
                      rot_head="ipdf", ipdf_pe_freqs=1)
    params = init(jax.random.PRNGKey(1), cfg)
    R = random_rotations(jax.random.PRNGKey(0), 1000)
    rng = np.random.default_rng(1)
    q = jnp.asarray(rng.normal(size=(5, 8)), jnp.float32)
    obj = jnp.asarray([0, 2, 1, 2, 0], jnp.int32)
    dense = rotation_logits(params, cfg, {"rot_emb": q}, R, obj)  # (5, 1000)
    v, i = jax.lax.top_k(dense, 4)
    prob = jnp.exp(v - jax.nn.logsumexp(dense, axis=1, keepdims=True))
    blocks, n = pad_library(rotation_features(R, cfg.ipdf_pe_freqs)[None], 256)  # 4 blocks, the last padded
    monkeypatch.setattr(matching, "IPDF_CHUNK_ELEMS", 5 * 16 * 64)  # 64 rotations per chunk: 16 chunks
    m = ipdf_match_blocks(params["rot_head"], q, blocks[0], obj, n, 4)
    np.testing.assert_array_equal(np.asarray(m.index), np.asarray(i))
    np.testing.assert_allclose(np.asarray(m.score), np.asarray(v), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.asarray(m.prob), np.asarray(prob), rtol=1e-4, atol=1e-7)


def test_ipdf_model_validates_and_predicts(tmp_path, models, scene):
    """An Implicit-PDF model (a checkpoint of the tiny preset with rot_head=ipdf): the run's
    validator scores it, and the estimator scores the library with the head: valid poses, TTA,
    top-k; refinement refused. (The training step itself is the loss's, tested in test_losses.)"""
    from sc6d_jax.model import init
    from sc6d_jax.train import StreamSettings, preset, save_checkpoint
    from sc6d_jax.train.validate import Validator

    cfg = preset("tiny")
    cfg = cfg.replace(model=dataclasses.replace(cfg.model, n_objects=2, rot_head="ipdf"),
                      stream=StreamSettings(batch_size=16, obj_ids=(1, 3)), z_range=(20.0, 400.0))
    params = init(jax.random.PRNGKey(0), cfg.model)
    rec = Validator(cfg, models, n=8, lib_size=600, batch=8)(params)
    assert 0.0 <= rec["val_ar"] <= 1.0 and 0.0 <= rec["val_rot_median_deg"] <= 180.0
    run = tmp_path / "ipdf"
    save_checkpoint(run, 1, params, {}, np.zeros(2, np.uint32), cfg.to_dict())
    est = Estimator.load(run, library_size=LIB, progress=False)
    assert est.library.emb.shape == (1, LIB, 9) and not (run / "library").exists()
    image, K, boxes, _ = scene
    out = est.predict(image, K, boxes, [1, 3, 3], tta=True, top_k=3, tta_mode="best")
    with pytest.raises(ValueError, match="Implicit-PDF"):  # fused TTA scores rotations with the SO(3) encoder
        est.predict(image, K, boxes, [1, 3, 3], tta=True)
    for p in out:
        assert _is_rotation(p.R) and _is_rotation(p.R_topk) and np.all(np.isfinite(p.t)) and p.t[2] > 0
        assert np.all(np.diff(p.score_topk) <= 1e-6) and 0.0 < p.prob <= 1.0
    with pytest.raises(ValueError, match="Implicit-PDF"):
        est.predict(image, K, boxes, [1, 3, 3], refine=True)


@pytest.mark.slow  # ~30 s of compiles for an option that stays off (README: "Depth from the rotation")
def test_depth_prior_decodes_with_the_matched_rotation(tmp_path, models):
    """model.z_rot: the estimator and the validator decode depth from the image's z logits plus
    the prior of the rotation each crop was matched to. A prior that says 'far' where the
    matched allocentric rotation has R[2,2] > 0 and 'near' where R[2,2] < 0 splits the decoded
    delta_z by that sign (two values, whatever the untrained image head says)."""
    from sc6d_jax.geometry import egocentric_to_allocentric, encode_translation
    from sc6d_jax.model import init, z_code
    from sc6d_jax.train import StreamSettings, preset, save_checkpoint
    from sc6d_jax.train.validate import Validator

    cfg = preset("tiny")
    cfg = cfg.replace(model=dataclasses.replace(cfg.model, n_objects=2, z_rot=True),
                      stream=StreamSettings(batch_size=16, obj_ids=(1, 3)), z_range=(20.0, 400.0))
    params = init(jax.random.PRNGKey(0), cfg.model)
    n, h, nb = 2, cfg.model.head_hidden, cfg.model.n_z_bins
    w1, w2, wo = np.zeros((n, 9, h), np.float32), np.zeros((n, h, h), np.float32), np.zeros((n, h, nb), np.float32)
    w1[:, 8, 0], w1[:, 8, 1] = 1.0, -1.0  # unit 0: relu(R22), unit 1: relu(-R22)
    w2[:, 0, 0] = w2[:, 1, 1] = 1.0
    wo[:, 0, nb - 4], wo[:, 1, 3] = 2000.0, 2000.0  # far / near bins, far above the image's logits
    zeros = lambda *s: jnp.zeros(s, jnp.float32)
    params["z_rot"] = {"fc1": {"w": jnp.asarray(w1), "b": zeros(n, h)}, "fc2": {"w": jnp.asarray(w2), "b": zeros(n, h)},
                       "out": {"w": jnp.asarray(wo), "b": zeros(n, nb)}}

    def split(r22, dz):
        far, near = r22 > 0.05, r22 < -0.05
        assert far.sum() >= 2 and near.sum() >= 2, (r22, dz)
        np.testing.assert_allclose(dz[far], np.median(dz[far]), rtol=1e-3)
        np.testing.assert_allclose(dz[near], np.median(dz[near]), rtol=1e-3)
        assert np.median(dz[far]) > 2 * np.median(dz[near])

    run = tmp_path / "zrot"
    save_checkpoint(run, 1, params, {}, np.zeros(2, np.uint32), cfg.to_dict())
    est = Estimator.load(run, library_size=LIB, progress=False)
    S, B = cfg.model.crop_size, 24
    rgb = np.random.default_rng(0).integers(0, 256, (B, S, S, 3), dtype=np.uint8)
    K = np.tile(np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]], np.float32), (B, 1, 1))
    center, side = np.tile(np.array([[300.0, 200.0]], np.float32), (B, 1)), np.full((B,), 120.0, np.float32)
    out = est.predict_crops(rgb, K, center, side, np.arange(B, dtype=np.int32) % 2)
    split(out["R_allo"][:, 2, 2], out["delta_z"])
    # fused TTA: every copy's prior reads the fused rotation (turned into the copy's frame, which
    # keeps R[2,2]), not the copy's own top-1, so the four copies agree and the split holds
    out = est.predict_crops(rgb, K, center, side, np.arange(B, dtype=np.int32) % 2, tta=True)
    split(out["R_allo"][:, 2, 2], out["delta_z"])

    v = Validator(cfg, models, n=32, lib_size=600, batch=16)
    pred = v.predict(params)
    d = v.data
    Ra = np.asarray(egocentric_to_allocentric(jnp.asarray(pred["R"], jnp.float32), jnp.asarray(pred["t"], jnp.float32)))
    _, dz = encode_translation(pred["t"], d["K"], d["center"], d["side"], S)
    split(Ra[:, 2, 2], np.asarray(z_code(dz, jnp.asarray(d["K"]), cfg.loss)))  # the crops' focal lengths differ


@pytest.mark.parametrize("pe_turns", [False, True])
def test_tta_copies_get_the_pe_map_the_model_was_trained_with(est, scene, monkeypatch, pe_turns):
    """TTA copy k of a crop is the crop turned by k quarter turns; its PE map turns with it for a
    model trained with pe_turns (turn_pe), and stays as it is for one trained without."""
    import sc6d_jax.model as M
    from sc6d_jax.geometry import crop_transform, pe_map, turn_pe
    from sc6d_jax.inference._predictor import predict_crops

    image, K, boxes, ids = scene
    seen = []
    real = M.apply

    def spy(params, mcfg, rgb, pe, *a, **kw):
        seen.append(np.asarray(pe))
        return real(params, mcfg, rgb, pe, *a, **kw)

    monkeypatch.setattr(M, "apply", spy)
    n = len(boxes)
    crops, center, side = est.make_crops(image, boxes, n)
    kw, blocks = est.crops_fn(n, tta=True)
    kw["mcfg"] = dataclasses.replace(est.mcfg, pe_turns=pe_turns)
    Kb = np.repeat(np.asarray(K, np.float32)[None], n, axis=0)
    with jax.disable_jit():
        predict_crops(est.params, blocks, est.library.R, crops, Kb, center, side, est.obj_index(ids), **kw)
    pe = np.asarray(pe_map(Kb, crop_transform(center, side, est.mcfg.crop_size), est.mcfg.crop_size))
    got = seen[0].reshape(4, n, *pe.shape[1:])
    for k in range(4):
        want = np.asarray(turn_pe(pe, k)) if pe_turns else pe
        np.testing.assert_allclose(got[k], want, atol=1e-5)
