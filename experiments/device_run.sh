#!/usr/bin/env bash
# One prepared run on a lent GPU machine (15 minutes of device time, no network there):
#
#   1. a smoke check: JAX sees the GPU, MuJoCo renders a training crop through EGL;
#   2. the `cpu` recipe on the 14 built-in objects at batch 256 (8x the preset's), for at most
#      TRAIN_S seconds, with the usual checkpoints and validation; the run comes back as
#      $OUT/gpu_run.tar.gz (its `sc6d carry` state: config, newest checkpoint, metrics,
#      validation shares), so that `sc6d demo --run` can score it on the development machine;
#   3. training steps/s of the `paper` and `cpu` presets (experiments/bench_train.py), with
#      pre-rendered batches and with the stream, into $OUT/bench_train.json.
#
# Each stage runs whatever the previous one did; logs go to $OUT. What travels: the tree, the
# built-in models (runs/objects/models) and, prepared on the development machine, the wheels
# missing there (.whl: mujoco, mujoco-core, glfw, pyopengl, trimesh for CPython 3.12) and the
# GL loader packages (.gl). Called as
#   run(command="bash experiments/device_run.sh", carry=[".whl", ".gl", "runs/objects"])
# Prepared once on the development machine (both folders git-ignored via .git/info/exclude):
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 -d .whl \
#     mujoco==4.0.1 mujoco-core==4.0.1 glfw pyopengl trimesh==5.2.0
#   (cd .gl && apt-get download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
# Locally (no install, tiny budget; tests/test_device_run.py does this):
#   SKIP_INSTALL=1 PY=.venv/bin/python OUT=/tmp/o TRAIN_STEPS=40 TRAIN_BATCH=8 WORKERS=1 BENCH=0 \
#   bash experiments/device_run.sh        (MODELS=DIR, PRESET=NAME change the objects and preset)
set -u
OUT=${OUT:?set OUT}
PY=${PY:-python3}
TRAIN_S=${TRAIN_S:-300}
TRAIN_STEPS=${TRAIN_STEPS:-8000}
TRAIN_BATCH=${TRAIN_BATCH:-256}
WORKERS=${WORKERS:-14}
BENCH=${BENCH:-1}
RUN=${RUN_DIR:-/tmp/gpu_run}
MODELS=${MODELS:-runs/objects/models}
PRESET=${PRESET:-cpu}
export MUJOCO_GL=egl PYOPENGL_PLATFORM=egl PYTHONUNBUFFERED=1
t0=$(date +%s)
stamp() { echo "[$(( $(date +%s) - t0 )) s] $*"; }

if [ "${SKIP_INSTALL:-0}" != 1 ]; then
  for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
  nv=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
  [ -f "$nv" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$nv
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || { echo "wheel install failed"; exit 1; }
  export PYTHONPATH=/tmp/site:$PWD
  nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm --format=csv
else
  export PYTHONPATH=$PWD
fi
stamp "setup done"

MODELS=$MODELS $PY - <<'EOF' 2>&1 | tee "$OUT/smoke.log"
import os
import jax, numpy as np, mujoco, trimesh
print("jax", jax.__version__, jax.devices(), "mujoco", mujoco.__version__, "trimesh", trimesh.__version__)
from sc6d_jax import data
from sc6d_jax.train.loop import _default_data_fns
cfg = _default_data_fns().stream_config(models_dir=os.environ["MODELS"], crop_size=64, batch_size=4, seed=0,
                                        workers=0, obj_ids=None, augment=True)
with data.CropStream(cfg, 0) as s:
    b = next(iter(s))
print("crop batch", {k: getattr(v, "shape", None) for k, v in b.items()} if isinstance(b, dict) else type(b))
EOF
stamp "smoke done"

timeout "$TRAIN_S" $PY -m sc6d_jax.cli train --models "$MODELS" --out "$RUN" --preset "$PRESET" \
  --workers "$WORKERS" --batch-size "$TRAIN_BATCH" --steps "$TRAIN_STEPS" --checkpoint-every 1000 \
  --no-progress --quiet > "$OUT/train.log" 2>&1
echo "train exit $?" | tee -a "$OUT/train.log"
stamp "training done"
tail -5 "$OUT/train.log"
if [ -d "$RUN/checkpoints" ]; then
  state=$(mktemp -d)/$(basename "$RUN")
  $PY -m sc6d_jax.cli carry --run "$RUN" --out "$state" \
    && tar -czf "$OUT/gpu_run.tar.gz" -C "$(dirname "$state")" "$(basename "$state")"
  $PY - "$RUN" <<'EOF'
import json, sys
for line in open(sys.argv[1] + "/metrics.jsonl"):
    r = json.loads(line)
    if "val_ar" in r:
        print({k: round(r[k], 3) if isinstance(r[k], float) else r[k] for k in
               ("step", "train_s", "val_ar", "val_rot_median_deg", "val_depth_rel_median") if k in r})
EOF
fi

if [ "$BENCH" = 1 ]; then
  timeout 170 $PY experiments/bench_train.py --models "$MODELS" --presets paper cpu --workers "$WORKERS" \
    --rounds 1 --windows 5 --window 20 --paper-windows 5 --paper-window 10 --json "$OUT/bench_train.json" \
    > "$OUT/bench.log" 2>&1
  echo "bench exit $?"; tail -30 "$OUT/bench.log"
fi
stamp "all done"
