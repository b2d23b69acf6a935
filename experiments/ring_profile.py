"""Does the network tell a turn about each of the object's own axes? The rings of the ground truth.

    python experiments/ring_profile.py --run runs/dumbbell --models runs/objects/models --out runs/rings \\
        [--step 3000] [--crops 128] [--plain] [--raw] [--gallery 13,8,9,12]

For each validation crop of the run (its own seed, as ``error_anatomy.py``) and each object axis
a in {x, y, z}, the ground truth (allocentric) is turned about a by every angle theta in steps of
5 degrees, R_gt Rot_a(theta), and two profiles are measured along that ring:

- the SO(3) encoder's self-similarity cos(enc(R_gt Rot_a(theta)), enc(R_gt)): near 1 all the
  way round means the encoder gives the whole ring one embedding, i.e. it treats the object as
  symmetric about a (right for a cylinder about its axis, a collapse for a dumbbell about its
  bar, where a small cube tells the turns apart);
- the score of the crop's image embedding along the ring, and where on the ring it peaks: the
  share of crops whose best angle is within 10 degrees of the ground truth, and the shares
  whose best angle is within 20 degrees of the quarter, half and three-quarter turns.

Per object and axis it prints and writes (``OUT/rings.csv``, ``OUT/rings.json``) the encoder's
smallest mean self-similarity along the ring (``enc_min_cos``), the peak shares, and the mean
score drop from the ground truth to the worst angle (``score_range``, in logits at tau = 0.1);
``OUT/rings.png`` draws the mean self-similarity and score profiles per object and axis;
``--gallery 13,8`` also draws ``OUT/turns.png``, those objects turned about their z axis by
quarter turns at the run's crop size (is the turn visible at all?). IPDF heads have no rotation
embedding: refused.
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

STEP_DEG = 5.0
COLUMNS = ("obj_id", "axis", "n", "enc_min_cos", "at_gt", "at_90", "at_180", "at_270", "score_range")


def ring_profiles(params, cfg, data: dict, step_deg: float = STEP_DEG, tau: float = 0.1) -> dict:
    """{(obj_id, axis): {"theta", "enc_cos" (A,), "score" (n, A)}} for the crops in ``data``
    (a Validator's data: rgb, pe, R, t, obj_idx, obj_id)."""
    import jax
    import jax.numpy as jnp

    from sc6d_jax.geometry import egocentric_to_allocentric, rot_x, rot_y, rot_z
    from sc6d_jax.model import apply, encode_rotations

    mcfg = cfg.model
    fwd = jax.jit(lambda p, rgb, pe, o: apply(p, mcfg, rgb, pe if mcfg.use_pe else None, o)["rot_emb"])
    emb = np.concatenate([np.asarray(fwd(params, jnp.asarray(data["rgb"][s:s + 64]), jnp.asarray(data["pe"][s:s + 64]),
                                         jnp.asarray(data["obj_idx"][s:s + 64])))
                          for s in range(0, len(data["rgb"]), 64)])
    Ra = np.asarray(egocentric_to_allocentric(jnp.asarray(data["R"], jnp.float32), jnp.asarray(data["t"], jnp.float32)))
    theta = np.arange(0.0, 360.0, step_deg)
    enc = jax.jit(lambda p, R, o: encode_rotations(p, mcfg, R, o), static_argnums=2)
    out = {}
    for oid in sorted(set(int(i) for i in data["obj_id"])):
        sel = np.flatnonzero(np.asarray(data["obj_id"]) == oid)
        o = int(data["obj_idx"][sel[0]])
        for name, rf in (("x", rot_x), ("y", rot_y), ("z", rot_z)):
            T = np.asarray(rf(jnp.deg2rad(jnp.asarray(theta, jnp.float32))))
            cands = (Ra[sel][:, None] @ T[None]).reshape(-1, 3, 3)
            e = np.asarray(enc(params, jnp.asarray(cands, jnp.float32), o)).reshape(len(sel), len(theta), -1)
            out[(oid, name)] = {"theta": theta, "enc_cos": np.einsum("nae,ne->a", e, e[:, 0]) / len(sel),
                                "score": np.einsum("nae,ne->na", e, emb[sel]) / tau}
    return out


def ring_rows(profiles: dict) -> list[dict]:
    rows = []
    for (oid, axis), p in profiles.items():
        th, s = p["theta"], p["score"]
        best = th[np.argmax(s, axis=1)]

        def near(c: float, tol: float) -> float:
            return float(np.mean(np.abs((best - c + 180.0) % 360.0 - 180.0) <= tol))

        rows.append({"obj_id": oid, "axis": axis, "n": int(s.shape[0]), "enc_min_cos": float(p["enc_cos"].min()),
                     "at_gt": near(0.0, 10.0), "at_90": near(90.0, 20.0), "at_180": near(180.0, 20.0),
                     "at_270": near(270.0, 20.0), "score_range": float(np.mean(s[:, 0] - s.min(axis=1)))})
    return rows


def figure(profiles: dict, path: Path) -> Path:
    from sc6d_jax.viz import save_figure
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    objs = sorted({o for o, _ in profiles})
    fig, axes = plt.subplots(2, len(objs), figsize=(3.2 * len(objs), 5.2), squeeze=False, sharex=True)
    for j, oid in enumerate(objs):
        for axis, colour in zip("xyz", ("C0", "C1", "C2")):
            p = profiles[(oid, axis)]
            axes[0, j].plot(p["theta"], p["enc_cos"], colour, label=f"about {axis}")
            axes[1, j].plot(p["theta"], (p["score"] - p["score"][:, :1]).mean(0), colour, label=f"about {axis}")
        axes[0, j].set_title(f"object {oid}")
        axes[1, j].set_xlabel("turn (deg)")
        axes[1, j].set_xticks([0, 90, 180, 270, 360])
    axes[0, 0].set_ylabel("encoder cos to ground truth")
    axes[1, 0].set_ylabel("image score - score at g.t.")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


def turn_gallery(models: Path, obj_ids: list[int], path: Path, size: int = 64) -> Path:
    """Each object rendered at one tilted view and turned about its own z axis by 0, 90, 180 and
    270 degrees, at ``size`` pixels (the crop the network sees, without clutter): whether the
    turn is visible at all."""
    from sc6d_jax.bop import load_models_info, model_path
    from sc6d_jax.geometry import rot_x, rot_z
    from sc6d_jax.render import Renderer, load_mesh
    from sc6d_jax.viz import save_figure
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    info = load_models_info(models)
    K = np.array([[60.0, 0, (size - 1) / 2], [0, 60.0, (size - 1) / 2], [0, 0, 1]])
    R0 = np.asarray(rot_x(np.radians(70.0))) @ np.asarray(rot_z(np.radians(20.0)))
    fig, axes = plt.subplots(len(obj_ids), 4, figsize=(6, 1.6 * len(obj_ids)), squeeze=False)
    for i, oid in enumerate(obj_ids):
        dist = 60.0 * info[oid].diameter / (0.75 * size)
        r = Renderer({oid: load_mesh(model_path(models, oid))}, size, size)
        try:
            for j in range(4):
                R = R0 @ np.asarray(rot_z(np.radians(90.0 * j)))
                axes[i, j].imshow(r.render([(oid, R, np.array([0.0, 0.0, dist]))], K, depth=False).rgb)
                axes[i, j].set_xticks([])
                axes[i, j].set_yticks([])
                if i == 0:
                    axes[i, j].set_title(f"+{90 * j} deg about z", fontsize=8)
        finally:
            r.close()
        axes[i, 0].set_ylabel(f"object {oid}", fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    p = checkpoint_parser(__doc__)
    p.add_argument("--crops", type=int, default=128, help="validation crops (default 128)")
    p.add_argument("--plain", action="store_true", help="plain backgrounds and no occluders instead of the run's stream")
    p.add_argument("--gallery", default=None, help="comma-separated object ids: also draw OUT/turns.png, each "
                   "object turned about its z axis by quarter turns at the run's crop size")
    a = p.parse_args(argv)

    def body() -> int:
        from sc6d_jax._io import atomic_write_text
        from sc6d_jax.train.validate import Validator

        if a.crops < 1:
            raise ValueError("--crops must be positive")
        step, params, cfg = load_scored_checkpoint(a)
        if cfg.model.rot_head != "so3":
            raise ValueError(f"{a.run}: rot_head {cfg.model.rot_head!r} has no rotation embedding to profile")
        ov = {"occlusion": 0.0, "background": "plain"} if a.plain else None
        v = Validator(cfg, a.models, n=a.crops, lib_size=1000, stream_overrides=ov)
        profiles = ring_profiles(params, cfg, v.data)
        rows = ring_rows(profiles)
        a.out.mkdir(parents=True, exist_ok=True)
        lines = [",".join(COLUMNS)] + [",".join(f"{r[c]:.4g}" if isinstance(r[c], float) else str(r[c])
                                                for c in COLUMNS) for r in rows]
        atomic_write_text(a.out / "rings.csv", "\n".join(lines) + "\n")
        atomic_write_text(a.out / "rings.json", json.dumps(
            {"run": str(a.run), "step": step, "raw": a.raw, "plain": a.plain, "rows": rows}, indent=1))
        figure(profiles, a.out / "rings.png")
        if a.gallery:
            turn_gallery(a.models, [int(x) for x in a.gallery.split(",")], a.out / "turns.png", cfg.model.crop_size)
        print(f"step {step}: obj axis  enc_min_cos  peak at g.t. / 90 / 180 / 270 deg  score range")
        for r in rows:
            print(f"{r['obj_id']:>12d}    {r['axis']}  {r['enc_min_cos']:10.2f}    {r['at_gt']:.2f} / {r['at_90']:.2f} / "
                  f"{r['at_180']:.2f} / {r['at_270']:.2f}       {r['score_range']:6.2f}")
        print(f"wrote {a.out / 'rings.csv'}, rings.json, rings.png")
        return 0

    return experiment_main("ring_profile", body)


if __name__ == "__main__":
    raise SystemExit(main())
