"""sc6d_jax.viz: sphere coordinates, the rotation-distribution figure, bar charts, PNG output."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sc6d_jax.viz import (
    ar_bar_chart,
    grouped_bar_chart,
    in_plane_angle,
    rotation_distribution_figure,
    save_figure,
    sphere_coords,
)


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_to(z: np.ndarray) -> np.ndarray:
    """Shortest-arc rotation taking e_z to the unit vector z (independent construction via
    scipy's align_vectors, which returns the minimal rotation for one vector pair)."""
    from scipy.spatial.transform import Rotation

    r, _ = Rotation.align_vectors([z], [[0.0, 0.0, 1.0]])
    return r.as_matrix()


@settings(max_examples=40, deadline=None)
@given(
    lon=st.floats(-np.pi, np.pi),
    lat=st.floats(-1.45, 1.45),
    roll=st.floats(-3.1, 3.1),
)
def test_sphere_coords_recover_direction_and_twist(lon, lat, roll):
    z = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    R = _rot_to(z) @ _rz(roll)
    glon, glat, groll = sphere_coords(R)
    assert np.isclose(glat, lat, atol=1e-6)
    assert np.isclose(np.angle(np.exp(1j * (glon - lon))), 0.0, atol=1e-6)
    assert np.isclose(np.angle(np.exp(1j * (groll - roll))), 0.0, atol=1e-6)


def test_in_plane_angle_is_batched_and_zero_for_pure_swings():
    R = np.stack([_rz(0.3), _rz(-2.0), _rot_to(np.array([1.0, 0.0, 0.0]))])
    np.testing.assert_allclose(in_plane_angle(R), [0.3, -2.0, 0.0], atol=1e-9)
    # the antipode (z -> -z) is defined through the swing about x
    assert np.isfinite(in_plane_angle(np.diag([1.0, -1.0, -1.0])))


def test_rotation_distribution_figure_draws_points_and_symmetric_rings(tmp_path):
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    rots = Rotation.random(50, random_state=1).as_matrix()
    probs = rng.random(50)
    sym = np.stack([_rz(k * np.pi / 2) for k in range(4)] + [np.diag([1.0, -1.0, -1.0])])
    fig = rotation_distribution_figure(rots[0], rots, probs, symmetries=sym, title="test")
    ax = fig.axes[0]
    offsets = [c.get_offsets().shape[0] for c in ax.collections]
    assert offsets[0] == 50  # the rotations
    assert offsets[1:] == [5, 5]  # ground truth + 4 equivalents (outline and coloured ring)
    sizes = ax.collections[0].get_sizes()
    assert sizes.max() > sizes.min()  # area follows probability
    p = save_figure(fig, tmp_path / "d.png")
    assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 5000
    assert list(tmp_path.iterdir()) == [p]  # nothing temporary left behind
    # no ground truth: points only
    fig2 = rotation_distribution_figure(None, rots, probs)
    assert len(fig2.axes[0].collections) == 1


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(R_gt=None, rotations=np.zeros((3, 3, 2)), probs=np.ones(3)), "rotations must be"),
        (dict(R_gt=None, rotations=np.stack([np.eye(3)] * 3), probs=np.ones(2)), "probs has 2 entries"),
        (dict(R_gt=None, rotations=np.stack([np.eye(3)] * 3), probs=[1, -1, 1]), "non-negative"),
        (dict(R_gt=2 * np.eye(3), rotations=np.stack([np.eye(3)]), probs=[1]), "R_gt is not a rotation"),
        (dict(R_gt=np.eye(3), rotations=np.stack([np.eye(3)]), probs=[1], symmetries=np.ones((2, 3))), "symmetries"),
    ],
)
def test_rotation_distribution_figure_rejects_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        rotation_distribution_figure(**kwargs)


def test_bar_charts(tmp_path):
    scores = {
        "bop19_average_recall": 0.5,
        "per_object": {"2": {"ar": 0.25, "ar_mssd": 0.5, "ar_mspd": 0.0, "ar_vsd": None},
                       "10": {"ar": 1.0, "ar_mssd": 1.0, "ar_mspd": 1.0, "ar_vsd": None}},
    }
    fig = ar_bar_chart(scores)
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.get_xticklabels()] == ["obj 2", "obj 10"]
    heights = [p.get_height() for p in ax.patches]
    assert heights == [0.25, 1.0, 0.5, 1.0, 0.0, 1.0]  # AR, AR_MSSD, AR_MSPD (no VSD: all None)
    assert save_figure(fig, tmp_path / "ar.png").stat().st_size > 1000
    with pytest.raises(ValueError, match="per_object"):
        ar_bar_chart({"bop19_average_recall": 0.1})
    with pytest.raises(ValueError, match="has 1 values for 2 labels"):
        grouped_bar_chart(["a", "b"], {"AR": [0.1]})
    fig = grouped_bar_chart(["a", "b"], {"AR": [0.1, 0.2]}, errors={"AR": [0.01, 0.02]})
    assert len(fig.axes[0].patches) == 2


def test_worst_targets_lists_and_draws_the_lowest_scoring_targets(models, gt_estimates, tmp_path):
    """On a rendered dataset with the ground truth as estimates: the first target of each image
    without an estimate, the second turned 90 deg about x, the rest exact. The missed targets
    come first, then the turned ones, the exact ones last; each tile shows no contour for a miss,
    the same silhouette as the ground truth's for an exact estimate, another for a turned one."""
    from scipy.spatial.transform import Rotation

    from sc6d_jax.bop import BopDataset, write_results_csv
    from sc6d_jax.metrics import evaluate_bop19
    from sc6d_jax.render._dataset import DatasetSpec, render_dataset
    from sc6d_jax.viz import _target_crop, lowest_scoring_targets, worst_targets_figure

    root = render_dataset(models, tmp_path / "ds", DatasetSpec(scenes=1, images_per_scene=2, objects_per_image=3,
                                                               width=160, height=120, seed=3), progress=False)
    ds = BopDataset(root)
    turn = Rotation.from_euler("x", 90.0, degrees=True).as_matrix()
    ests, kinds = gt_estimates(ds, lambda k, g: None if k == 0 else (g.R @ turn if k == 1 else g.R, g.t))
    results = write_results_csv(tmp_path / "r.csv", ests)
    scores = evaluate_bop19(ds, ests, renderer=None)
    n_targets = scores["counts"]["targets"]
    assert n_targets == len(kinds) + 2 and kinds.count(1) == 2

    rows = lowest_scoring_targets(ds, ests, scores, n=n_targets)
    assert len(rows) == n_targets
    assert [r["missed"] for r in rows[:2]] == [True, True] and not any(r["missed"] for r in rows[2:])
    assert [r["share"] for r in rows] == sorted(r["share"] for r in rows)
    assert rows[-1]["share"] == pytest.approx(1.0) and rows[-1]["rot_deg"] < 1e-3
    assert len(lowest_scoring_targets(ds, ests, scores, n=3)) == 3

    tile, cols = 64, 3
    pic = worst_targets_figure(root, results, scores, n=n_targets, columns=cols, tile=tile)
    th, tw = 18 + tile + 4, 2 * tile + 4
    assert pic.shape == (-(-n_targets // cols) * th, cols * tw, 3) and pic.dtype == np.uint8
    for i, r in enumerate(rows):
        y, x = (i // cols) * th + 2 + 18, (i % cols) * tw + 2
        raw = _target_crop(ds.load_rgb(r["scene_id"], r["im_id"]),
                           ds.scene_gt_info(r["scene_id"])[r["im_id"]][r["gt_id"]].bbox_visib, tile)
        drawn = [np.any(pic[y:y + tile, x + j * tile:x + (j + 1) * tile] != raw, axis=-1) for j in (0, 1)]
        assert drawn[1].sum() > 20  # the ground truth's contour
        if r["missed"]:
            assert not drawn[0].any()
        elif r["rot_deg"] < 1e-3:  # the same contour (anti-aliased in another colour: a few edge pixels)
            assert (drawn[0] != drawn[1]).sum() <= 0.05 * drawn[1].sum()
        elif r["rot_deg"] > 80:
            assert (drawn[0] != drawn[1]).sum() > 0.2 * drawn[1].sum()
    with pytest.raises(ValueError, match="per_target"):
        lowest_scoring_targets(ds, ests, {"bop19_average_recall": 0.1})
