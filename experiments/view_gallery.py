"""What the view head reads back: augmented crops, their clean views and the model's reconstructions.

    python experiments/view_gallery.py --run runs/ring13/view --models runs/objects/models --out runs/view13.png \\
        [--step 3000] [--crops 12] [--seed 99]

A run trained with ``model.view_head=V`` and ``loss.w_view`` decodes a clean view of the target
(the crop before its colour augmentation, black off the visible target; ``stream.view``) from
the rotation head's hidden layer. This draws ``--crops`` crops of the full stream (the run's
objects and settings, another seed, full difficulty) in rows of four triples: the crop the
network sees, the clean view it is asked for, and the view it gives back (clipped to [0, 1]),
each at the crop's size. Whether the small parts that break a near-symmetry come back (the
dumbbell's magenta cube) tells whether the vector the rotation is read from carries them.
Prints the view loss of these crops (the run's bootstrapped L2). Runs without a view head are
refused.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from sc6d_jax._subprocess import experiment_main  # noqa: E402
from error_anatomy import checkpoint_parser, load_scored_checkpoint  # noqa: E402

#: The stream's batch index the crops are drawn at: past any curriculum, at full difficulty.
FULL_BATCH = 10**7
PER_ROW = 4


def gallery_batch(cfg, models: Path, n: int, seed: int) -> dict:
    """``n`` crops of ``cfg``'s stream with clean views of the model's view_head side."""
    from sc6d_jax.data import CropStream, StreamConfig
    from sc6d_jax.train.loop import stream_fields

    fields = {**stream_fields(cfg, models, 0), "view": cfg.model.view_head, "workers": 0}
    with CropStream(StreamConfig(**fields, batch_size=n, seed=seed)) as s:
        return s.batch(FULL_BATCH)


def draw(rgb: np.ndarray, view: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """uint8 RGB grid: rows of PER_ROW (crop, clean view, reconstruction) triples, views
    enlarged to the crop's side by pixel repetition, 2-px white gaps."""
    n, S = rgb.shape[:2]
    f = S // view.shape[1]
    up = lambda a: np.repeat(np.repeat(a, f, axis=1), f, axis=2)  # noqa: E731
    recon = np.clip(np.rint(pred * 255.0), 0, 255).astype(np.uint8)
    tiles = [np.concatenate([rgb[i], np.full((S, 2, 3), 255, np.uint8), up(view)[i], np.full((S, 2, 3), 255, np.uint8),
                             up(recon)[i]], axis=1) for i in range(n)]
    blank = np.full_like(tiles[0], 255)
    rows = []
    for r in range(0, n, PER_ROW):
        row = tiles[r:r + PER_ROW] + [blank] * (PER_ROW - len(tiles[r:r + PER_ROW]))
        rows.append(np.concatenate([np.concatenate([t, np.full((S, 8, 3), 255, np.uint8)], axis=1) for t in row], axis=1))
    gap = np.full((4, rows[0].shape[1], 3), 255, np.uint8)
    return np.concatenate([x for row in rows for x in (row, gap)][:-1], axis=0)


def main(argv: list[str] | None = None) -> int:
    p = checkpoint_parser(__doc__)
    p.add_argument("--crops", type=int, default=12, help="crops to draw (default 12)")
    p.add_argument("--seed", type=int, default=99, help="the stream's seed for these crops (default 99)")
    a = p.parse_args(argv)

    def body() -> int:
        import jax.numpy as jnp

        from sc6d_jax._io import atomic_write_png
        from sc6d_jax.model import apply, view_loss

        if a.crops < 1:
            raise ValueError("--crops must be positive")
        if a.out.suffix.lower() != ".png":
            raise ValueError(f"--out must name a .png file, got {a.out}")
        step, params, cfg = load_scored_checkpoint(a)
        if not cfg.model.view_head or "view_head" not in params:
            raise ValueError(f"{a.run}: the run's model has no view head (train with --set model.view_head=V "
                             "--set loss.w_view=W)")
        b = gallery_batch(cfg, a.models, a.crops, a.seed)
        out = apply(params, cfg.model, jnp.asarray(b["rgb"]), jnp.asarray(b["pe"]) if cfg.model.use_pe else None,
                    jnp.asarray(b["obj_idx"]))
        loss = float(view_loss(out["view"], b["view"], cfg.loss.view_top))
        img = draw(b["rgb"], b["view"], np.asarray(out["view"], np.float32))
        atomic_write_png(a.out, img)
        print(f"step {step}: view loss {loss:.4f} over {a.crops} crops (top {cfg.loss.view_top:g} of the pixels); "
              f"wrote {a.out}")
        return 0

    return experiment_main("view_gallery.py", body)


if __name__ == "__main__":
    raise SystemExit(main())
