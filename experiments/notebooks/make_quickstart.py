"""Writes quickstart.ipynb (outputs stripped): ``python experiments/notebooks/make_quickstart.py``."""

from pathlib import Path

import nbformat as nbf

cells = [
    nbf.v4.new_markdown_cell(
        "# sc6d-jax quickstart\n\n"
        "Built-in objects -> a rendered BOP test image -> a `tiny` model trained for a few hundred steps on one "
        "asymmetric object -> poses for the image -> an overlay picture -> the rotation distribution on a sphere "
        "(the paper's overview figure: the top-k library rotations as points, coloured by probability).\n\n"
        "Runs on a CPU in a few minutes. `SC6D_NB_STEPS` sets the training steps (default 400)."
    ),
    nbf.v4.new_code_cell(
        "import os, tempfile, dataclasses\n"
        "from pathlib import Path\n"
        "import numpy as np\n"
        "import matplotlib\n"
        "import matplotlib.pyplot as plt\n"
        "from sc6d_jax import Estimator, bop, geometry\n"
        "from sc6d_jax.objects import write_models\n"
        "from sc6d_jax.render._dataset import DatasetSpec, render_dataset\n"
        "from sc6d_jax.train import preset, train\n"
        "from sc6d_jax.viz import draw_overlay\n"
        "\n"
        "work = Path(tempfile.mkdtemp(prefix='sc6d-quickstart-'))\n"
        "steps = int(os.environ.get('SC6D_NB_STEPS', '400'))\n"
        "OBJ = 1  # the asymmetric L-bracket\n"
        "models = write_models(work / 'models')\n"
        "print(work)"
    ),
    nbf.v4.new_markdown_cell("## A rendered BOP test image"),
    nbf.v4.new_code_cell(
        "ds_dir = render_dataset(models, work / 'dataset', DatasetSpec(scenes=1, images_per_scene=2, objects_per_image=1,\n"
        "                        distractors=2, obj_ids=(OBJ,), seed=5), progress=False)\n"
        "ds = bop.BopDataset(ds_dir)\n"
        "image, K = ds.load_rgb(1, 0), ds.scene_camera(1)[0].K\n"
        "gt, info = ds.scene_gt(1)[0][0], ds.scene_gt_info(1)[0][0]\n"
        "plt.imshow(image); plt.axis('off'); plt.title('rendered test image');"
    ),
    nbf.v4.new_markdown_cell(
        "## Train the `tiny` preset on one object\n\n"
        "A curriculum longer than the run keeps the crops on plain backgrounds without occluders, which a tiny "
        "network learns in a few hundred steps."
    ),
    nbf.v4.new_code_cell(
        "cfg = preset('tiny', steps=steps, checkpoint_every=steps, log_every=50)\n"
        "cfg = cfg.replace(stream=dataclasses.replace(cfg.stream, obj_ids=(OBJ,), occlusion=0.0, curriculum=10**6))\n"
        "run = work / 'run'\n"
        "train(cfg, models, run, progress=False, verbose=False, workers=1)\n"
        "import json\n"
        "m = [json.loads(l) for l in (run / 'metrics.jsonl').read_text().splitlines()]\n"
        "plt.plot([r['step'] for r in m], [r['loss_rot'] for r in m]); plt.xlabel('step'); plt.ylabel('InfoNCE loss');"
    ),
    nbf.v4.new_markdown_cell("## Predict the pose from the image, K and the box"),
    nbf.v4.new_code_cell(
        "est = Estimator.load(run, library_size=20_000, progress=False)\n"
        "box = np.array([info.bbox_visib], float)\n"
        "pred = est.predict(image, K, box, [OBJ], top_k=200)[0]\n"
        "err_R = float(np.degrees(geometry.geodesic_angle(pred.R, gt.R)))\n"
        "err_t = float(np.linalg.norm(pred.t - gt.t))\n"
        "print(f'rotation error {err_R:.1f} deg, translation error {err_t:.1f} mm (distance {gt.t[2]:.0f} mm)')\n"
        "assert np.all(np.isfinite(pred.R)) and np.all(np.isfinite(pred.t))"
    ),
    nbf.v4.new_code_cell(
        "overlay = draw_overlay(image, K, [pred], str(models))\n"
        "plt.figure(figsize=(10, 4)); plt.subplot(1, 2, 1); plt.imshow(image); plt.axis('off'); plt.title('input')\n"
        "plt.subplot(1, 2, 2); plt.imshow(overlay); plt.axis('off'); plt.title('silhouette at the estimated pose');"
    ),
    nbf.v4.new_markdown_cell(
        "## The rotation distribution\n\n"
        "Each of the top-200 library rotations is drawn as the direction of the object's z axis (Mollweide "
        "projection: longitude, latitude) coloured by the in-plane angle about it, sized by probability; the ring "
        "marks the ground truth (`sc6d_jax.viz.rotation_distribution_figure`, also used by `sc6d eval --figures`). A symmetric object would show several equally likely modes."
    ),
    nbf.v4.new_code_cell(
        "from sc6d_jax.viz import rotation_distribution_figure\n"
        "fig = rotation_distribution_figure(gt.R, pred.R_topk, pred.prob_topk, title='top-200 rotations')\n"
        "fig"
    ),
]
nb = nbf.v4.new_notebook(cells=cells, metadata={"kernelspec": {"name": "python3", "display_name": "Python 3", "language": "python"}})
out = Path(__file__).with_name("quickstart.ipynb")
nbf.write(nb, out)
print(f"wrote {out}")
