"""experiments/step_profile.py: the kinds of the optimised HLO's operations, and a real profile of
the tiny preset's compiled step."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "experiments"))

import step_profile  # noqa: E402


def test_op_kinds_sorts_operations_by_what_they_compute():
    hlo = "\n".join([
        '  %ynn_fusion.3 = f32[16,3,3,16]{3,2,1,0} fusion(%a, %b), kind=kCustom, calls=%f3, '
        'metadata={op_name="jit(step_fn)/transpose(jvp())/conv_general_dilated"}',
        '  %ynn_fusion.4 = f32[32,8,8,16]{3,2,1,0} fusion(%a, %b), kind=kCustom, calls=%f4, '
        'metadata={op_name="jit(step_fn)/jvp()/conv_general_dilated"}',
        '  %dot.7 = f32[32,128]{1,0} dot(%x, %w), metadata={op_name="jit(step_fn)/jvp()/dot_general"}',
        '  %ynn_fusion.9 = f32[32]{0} fusion(%x), kind=kCustom, calls=%f9, '
        'metadata={op_name="jit(step_fn)/transpose(jvp())/reduce_sum"}',
        '  %transpose_copy_fusion.1 = f32[5,64,64,32]{3,2,1,0} fusion(%m), kind=kLoop, calls=%f1',
        '  ROOT %add_maximum_fusion = f32[32,16]{1,0} fusion(%p, %q), kind=kLoop, calls=%f2',
    ])
    k = step_profile.op_kinds(hlo)
    assert k["ynn_fusion.3"] == "convolution, gradient"
    assert k["ynn_fusion.4"] == "convolution, forward"
    assert k["dot.7"] == "matrix product, forward"
    assert k["ynn_fusion.9"].startswith("reduction")
    assert k["transpose_copy_fusion.1"].startswith("layout copy")
    assert k["add_maximum_fusion"].startswith("element-wise")


def test_profiles_the_tiny_preset(tmp_path, models):
    """A model of two objects (the config's object count follows --obj-ids)."""
    out = tmp_path / "p.json"
    r = subprocess.run([sys.executable, str(REPO / "experiments" / "step_profile.py"), "--preset", "tiny",
                        "--obj-ids", "1", "2", "--models", str(models), "--steps", "2", "--json", str(out)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(out.read_text())
    assert res["obj_ids"] == [1, 2]
    assert res["step_ms_median"] > 0 and res["gflop_per_step"] > 0
    by_kind = res["ms_per_step_by_kind"]
    assert by_kind.get("convolution, forward", 0) > 0 and by_kind.get("convolution, gradient", 0) > 0
    assert "median step" in r.stdout


def test_bad_input(tmp_path):
    r = subprocess.run([sys.executable, str(REPO / "experiments" / "step_profile.py"), "--models",
                        str(tmp_path / "none"), "--steps", "1"], capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "none" in r.stderr
