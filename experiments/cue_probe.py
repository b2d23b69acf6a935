"""Does the network see the dumbbell's small cube? Linear probes of its layers for the cube's side.

    python experiments/cue_probe.py --run runs/ring13/cpu --models runs/objects/models [--step 3000] \\
        [--crops 3072] [--seed 77] [--out runs/cue13.json]

The dumbbell (obj 13, or a models folder from ``dumbbell_variant.py``) is told from its turns
about its bar only by a small magenta cube beside the bar. For crops of the run's stream (another
seed, full difficulty; ``--plain``: plain backgrounds, no occluders), the label is the side of the bar the cube's centre projects to in the
crop (the sign of the cross product of the bar's image direction and the cube's offset from the
bar's centre; ``cube_side``): what a network that tells the turns apart must see. Crops where
the cube lies within ``--margin`` pixels of the bar's line (seen end-on or nearly behind it) are
left out. A ridge-regression probe of each of the network's representations (the input pixels,
the decoder's features at S/4 after the mask gate, the map the rotation head flattens, its hidden
layer, the rotation embedding), trained on half the crops and scored on the other half, gives the
fraction of held-out crops whose side it tells: 0.5 is chance. If the rotation head's map tells
the side but the embedding does not, the head does not use what it is given; if no layer does,
the features never pick the cube up. Prints a table and writes it as JSON to ``--out``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from sc6d_jax._subprocess import experiment_main  # noqa: E402
from error_anatomy import checkpoint_parser, load_scored_checkpoint  # noqa: E402

DUMBBELL = 13
#: The small cube's centre on the dumbbell's x axis, mm (sc6d_jax/objects/_builtin.py); the bar is z.
CUBE_X = 14.0
LAYERS = ("pixels", "features", "rot_map", "rot_hidden", "rot_emb")


def cube_side(R: np.ndarray, t: np.ndarray, K_B: np.ndarray, cube_x: float = CUBE_X) -> tuple[np.ndarray, np.ndarray]:
    """(side in {-1, +1}, distance in px of the cube's centre from the bar's image line) per crop,
    for poses R (B,3,3), t (B,3) mm and crop intrinsics K_B (B,3,3): the bar runs along the
    object's z axis through its origin, the cube's centre sits at (cube_x, 0, 0)."""
    def proj(X):
        uv = np.einsum("bij,bj->bi", K_B, X)
        return uv[:, :2] / uv[:, 2:3]

    R, t, K_B = (np.asarray(a, np.float64) for a in (R, t, K_B))
    o = proj(t)
    z = proj(t + 50.0 * R[:, :, 2]) - o  # the bar's direction in the image
    c = proj(t + cube_x * R[:, :, 0]) - o
    cross = z[:, 0] * c[:, 1] - z[:, 1] * c[:, 0]
    dist = np.abs(cross) / np.maximum(np.linalg.norm(z, axis=1), 1e-9)
    return np.where(cross >= 0, 1.0, -1.0), dist


def probe_accuracy(X: np.ndarray, y: np.ndarray, ridge: float = 1.0) -> float:
    """Held-out accuracy of a ridge-regression probe of y in {-1, +1} on X (N, D): fit on the
    first half, scored on the second; features standardised on the first half, the ridge chosen
    from (0.1, 1, 10, 100) x ``ridge`` by a split of the first half."""
    X = np.asarray(X, np.float64).reshape(len(X), -1)
    n = len(X) // 2
    mu, sd = X[:n].mean(0), X[:n].std(0) + 1e-6
    X = (X - mu) / sd

    def fit(A, b, lam):
        A1 = np.hstack([A, np.ones((len(A), 1))])
        if A1.shape[1] <= len(A1):
            return np.linalg.solve(A1.T @ A1 + lam * np.eye(A1.shape[1]), A1.T @ b)
        return A1.T @ np.linalg.solve(A1 @ A1.T + lam * np.eye(len(A1)), b)  # the dual for wide features

    def acc(w, A, b):
        return float(np.mean(np.sign(np.hstack([A, np.ones((len(A), 1))]) @ w) == b))

    m = n // 2
    lams = [ridge * f * X.shape[1] / 100.0 for f in (0.1, 1.0, 10.0, 100.0)]
    best = max(lams, key=lambda lam: acc(fit(X[:m], y[:m], lam), X[m:n], y[m:n]))
    return acc(fit(X[:n], y[:n], best), X[n:], y[n:])


def representations(params, mcfg, rgb: np.ndarray, pe: np.ndarray, obj_idx: np.ndarray) -> dict[str, np.ndarray]:
    """The network's layers for the crops: {layer: (N, ...)} for :data:`LAYERS`."""
    import jax
    import jax.numpy as jnp

    from sc6d_jax.model._encoder import backbone, decoder
    from sc6d_jax.model._network import RGB_MEAN, RGB_STD, normalize_rgb
    from sc6d_jax.model._pose_decoder import pose_decoder
    from sc6d_jax.model._rotation import _l2n

    @jax.jit
    def fwd(p, rgb, pe, o):
        x = (normalize_rgb(rgb) - jnp.asarray(RGB_MEAN)) / jnp.asarray(RGB_STD)
        if mcfg.use_pe:
            x = jnp.concatenate([x, pe.astype(jnp.float32)], axis=-1)
        feat, mask_logit = decoder(p["decoder"], mcfg, backbone(p["backbone"], mcfg, x), o)
        if mcfg.mask_gate:
            feat = feat * jax.nn.sigmoid(mask_logit)[..., None]
        rot, _, _, h, m, _ = pose_decoder(p["pose_decoder"], mcfg, feat, mask_logit, pe if mcfg.use_pe else None,
                                       return_hidden=True, return_map=True, obj_idx=o)
        return {"features": feat, "rot_map": m, "rot_hidden": h, "rot_emb": _l2n(rot)}

    parts = [fwd(params, jnp.asarray(rgb[s:s + 64]), jnp.asarray(pe[s:s + 64]), jnp.asarray(obj_idx[s:s + 64]))
             for s in range(0, len(rgb), 64)]
    out = {k: np.concatenate([np.asarray(q[k], np.float32) for q in parts]) for k in parts[0]}
    out["pixels"] = rgb.astype(np.float32) / 255.0
    return out


def main(argv: list[str] | None = None) -> int:
    p = checkpoint_parser(__doc__)
    p.set_defaults(out=None)
    for action in p._actions:
        if action.dest == "out":
            action.required = False
    p.add_argument("--crops", type=int, default=3072, help="crops (half fit the probes, half score them)")
    p.add_argument("--seed", type=int, default=77)
    p.add_argument("--cube-x", type=float, default=CUBE_X,
                   help=f"mm: the cube's centre on the object's x axis (default {CUBE_X:g}; dumbbell_variant.py's --x)")
    p.add_argument("--plain", action="store_true", help="crops on plain backgrounds without occluders")
    p.add_argument("--margin", type=float, default=1.0, help="px: crops whose cube lies nearer the bar's line are left out")
    a = p.parse_args(argv)

    def body() -> int:
        from sc6d_jax._io import atomic_write_json
        from sc6d_jax.data import CropStream, StreamConfig
        from sc6d_jax.train.loop import stream_fields

        if a.crops < 64:
            raise ValueError("--crops must be at least 64")
        step, params, cfg = load_scored_checkpoint(a)
        ids = list(cfg.stream.obj_ids or [])
        if DUMBBELL not in ids:
            raise ValueError(f"{a.run}: the run did not train the dumbbell (obj {DUMBBELL}); its objects: {ids}")
        fields = {**stream_fields(cfg, a.models, 0), "workers": 0, "obj_ids": (DUMBBELL,), "curriculum": 0}
        if a.plain:
            fields.update(background="plain", occlusion=0.0)
        batches = []
        with CropStream(StreamConfig(**fields, batch_size=64, seed=a.seed)) as s:
            for i in range(-(-a.crops // 64)):
                batches.append(s.batch(i))
        b = {k: np.concatenate([x[k] for x in batches])[:a.crops] for k in ("rgb", "pe", "R", "t", "K_B")}
        side, dist = cube_side(b["R"], b["t"], b["K_B"], a.cube_x)
        # the crops' quarter turns move the image, not R and t: the side is that of the unturned
        # crop, and a turn keeps it (a rotation of the plane keeps the cross product's sign)
        keep = dist >= a.margin
        obj_idx = np.full(a.crops, ids.index(DUMBBELL), np.int32)
        reps = representations(params, cfg.model, b["rgb"], b["pe"], obj_idx)
        rows = {name: probe_accuracy(reps[name][keep], side[keep]) for name in LAYERS}
        print(f"step {step}, {int(keep.sum())} of {a.crops} crops (cube >= {a.margin:g} px off the bar's line), "
              f"{np.mean(side[keep] > 0):.2f} on one side")
        print("layer        held-out accuracy of the cube's side (0.5 = chance)")
        for name in LAYERS:
            print(f"{name:12s} {rows[name]:.3f}")
        if a.out is not None:
            atomic_write_json(a.out, {"run": str(a.run), "step": step, "crops": int(keep.sum()), "accuracy": rows})
        return 0

    return experiment_main("cue_probe.py", body)


if __name__ == "__main__":
    raise SystemExit(main())
