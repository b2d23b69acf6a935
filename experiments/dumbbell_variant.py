"""The built-in dumbbell (obj 13) with a larger cube on its bar, as a one-object models folder.

    python experiments/dumbbell_variant.py --out runs/objects_bigcube [--size 40] [--x 28]

The built-in dumbbell is told from its turns about its bar only by a small magenta cube (20 mm,
centred 14 mm from the bar's axis). This writes the same object with a second, larger magenta
cube (``--size`` mm, centred ``--x`` mm from the axis, at the small one's height) as a BOP
``models/`` folder holding obj 13 alone (PLY in mm with vertex colours and its
models_info.json, no symmetries), so that a run can ask whether the network learns the turn
when its cue is larger (README, "The dumbbell's whole ring"). The object stays centred on its
bounding box, as the built-in asymmetric objects are.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sc6d_jax._subprocess import experiment_main  # noqa: E402


def variant_mesh(size: float = 40.0, x: float = 28.0):
    """(the built-in dumbbell with the larger cube added, that object's BuiltinObject)."""
    import trimesh

    from sc6d_jax.objects._builtin import _colour, _placed, builtin_objects

    o = next(b for b in builtin_objects() if b.obj_id == 13)
    m = o.mesh
    c = np.asarray(m.visual.vertex_colors[:, :3], int)
    cube = (c[:, 0] > c[:, 1] + 40) & (c[:, 2] > c[:, 1] + 40)  # the small cube is the magenta part
    if not cube.any():
        raise RuntimeError("the built-in dumbbell has no magenta cube: the object set changed")
    centre = (m.vertices[cube].min(0) + m.vertices[cube].max(0)) / 2
    big = _placed(trimesh.creation.box((size, size, size)), (x, centre[1], centre[2]))
    new = trimesh.util.concatenate([m, _colour(big, tuple(int(v) for v in c[cube][0]))])
    new = trimesh.Trimesh(new.vertices, new.faces, vertex_colors=new.visual.vertex_colors, process=False)
    lo, hi = new.bounds
    new.apply_translation(-(lo + hi) / 2)
    return new, dataclasses.replace(o, mesh=new)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, type=Path, help="the models folder to write (must not exist)")
    p.add_argument("--size", type=float, default=40.0, help="the larger cube's side, mm (default 40)")
    p.add_argument("--x", type=float, default=28.0, help="its centre's distance from the bar's axis, mm (default 28)")
    a = p.parse_args(argv)

    def body() -> int:
        import trimesh

        from sc6d_jax._io import atomic_directory, atomic_write_bytes
        from sc6d_jax.bop import write_models_info
        from sc6d_jax.objects._builtin import model_info

        if not (a.size > 0 and a.x >= 0):
            raise ValueError(f"--size must be positive and --x non-negative, got {a.size} and {a.x}")
        if a.out.exists():
            raise FileExistsError(f"{a.out} exists; choose a new folder")
        mesh, obj = variant_mesh(a.size, a.x)
        with atomic_directory(a.out) as tmp:
            atomic_write_bytes(tmp / "obj_000013.ply", trimesh.exchange.ply.export_ply(mesh, encoding="binary", vertex_normal=False))
            write_models_info(tmp / "models_info.json", {13: model_info(obj)})
        print(f"wrote {a.out}: obj 13 with a {a.size:g} mm cube {a.x:g} mm from its bar (diameter "
              f"{model_info(obj).diameter:.1f} mm)")
        return 0

    return experiment_main("dumbbell_variant", body)


if __name__ == "__main__":
    raise SystemExit(main())
