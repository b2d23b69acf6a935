#!/usr/bin/env bash
# One-step set-up and run for sc6d-jax on a fresh Debian/Ubuntu machine with Python >= 3.11.
#
#   bash experiments/bootstrap.sh demo [ARGS]   # the main job (sc6d demo)
#   bash experiments/bootstrap.sh test [ARGS]   # the test suite (pytest)
#
# Idempotent: installs the system packages MuJoCo's off-screen EGL rendering needs on a
# CPU-only machine (Mesa's software rasteriser) only when they are missing, creates .venv
# only once, and reinstalls the Python packages only when pyproject.toml changed.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
MODE="${1:-}"
shift || true
case "$MODE" in
  demo|test|shell) ;;
  *) echo "usage: bash experiments/bootstrap.sh {demo|test} [ARGS...]" >&2; exit 2 ;;
esac

say() { printf '[bootstrap] %s\n' "$*" >&2; }

PYTHON="${PYTHON:-}"
if [[ -z "$PYTHON" ]]; then
  for cand in python3.11 python3.12 python3.13 python3; do
    if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
      PYTHON="$cand"; break
    fi
  done
fi
if [[ -z "$PYTHON" ]]; then
  say "error: Python >= 3.11 not found (set PYTHON=/path/to/python3.11)"; exit 1
fi

# --- system packages -------------------------------------------------------------------
need_pkgs=()
# ldconfig's list is read once: `ldconfig -p | grep -q` under pipefail fails at random (grep
# quits at the first match, ldconfig dies of SIGPIPE) and reinstalled packages that were there.
LDCACHE="$(ldconfig -p 2>/dev/null || true)"
have_lib() { [[ "$LDCACHE" == *"$1"* ]]; }
have_lib 'libEGL.so.1 '      || need_pkgs+=(libegl1)
have_lib 'libEGL_mesa.so.0'  || need_pkgs+=(libegl-mesa0)
have_lib 'libOpenGL.so.0'    || need_pkgs+=(libopengl0)
have_lib 'libGL.so.1 '       || need_pkgs+=(libgl1)
[[ -n "$(ls /usr/lib/*/dri/swrast_dri.so /usr/lib/dri/swrast_dri.so 2>/dev/null)" ]] || need_pkgs+=(libgl1-mesa-dri)
"$PYTHON" -c 'import ensurepip, venv' >/dev/null 2>&1 || need_pkgs+=("python3-venv")

if ((${#need_pkgs[@]})); then
  if [[ $(id -u) -eq 0 ]]; then SUDO=""
  elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then SUDO="sudo -n"
  else
    say "error: missing system packages: ${need_pkgs[*]}"
    say "they are needed for MuJoCo's off-screen EGL rendering; install them as root:"
    say "  sudo apt-get install -y --no-install-recommends ${need_pkgs[*]}"
    exit 1
  fi
  say "installing system packages: ${need_pkgs[*]}"
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get update -qq
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need_pkgs[@]}" >/dev/null
fi

# --- Python environment ----------------------------------------------------------------
VENV="$ROOT/.venv"
if [[ ! -x "$VENV/bin/python" ]]; then
  say "creating $VENV"
  "$PYTHON" -m venv "$VENV"
fi
STAMP="$VENV/.sc6d-installed"
WANT="$(cat pyproject.toml | sha256sum | cut -d' ' -f1)"
if [[ ! -f "$STAMP" || "$(cat "$STAMP")" != "$WANT" ]] || ! "$VENV/bin/python" -c 'import sc6d_jax' 2>/dev/null; then
  say "installing Python packages (pip install -e .[dev]); the first time takes a few minutes"
  "$VENV/bin/python" -m pip install -q --disable-pip-version-check --upgrade pip
  "$VENV/bin/python" -m pip install -q --disable-pip-version-check -e ".[dev]"
  echo "$WANT" > "$STAMP"
fi

export MUJOCO_GL="${MUJOCO_GL:-egl}"
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-egl}"
export PATH="$VENV/bin:$PATH"

case "$MODE" in
  demo)
    exec "$VENV/bin/sc6d" demo "$@" ;;
  test)
    set +e
    "$VENV/bin/python" -m pytest "$@"
    rc=$?
    # pytest's 5 means "no test collected": a selection that matched nothing is not a failure.
    if [[ $rc -eq 5 ]]; then rc=0; fi
    exit $rc ;;
  shell)
    exec bash "$@" ;;
esac
