#!/usr/bin/env bash
# One-command setup on Debian (as root) or any Linux with the system packages already present.
#   - Debian's libllvm19 for Dr.Jit's LLVM backend (the system's LLVM 15 crashes Mitsuba's llvm variants)
#   - a virtual environment in .venv with a torch/torchvision pair that import together
#   - this package, editable, with its dev extras
#   - Blender as a Python module (bpy) in .venv-blender, for the test that opens the exported GLB in Blender
#   - Node.js, Chromium and npm packages (the glTF validator, three.js, esbuild) in .tools for the glTF
#     export's checks and its viewer page
#   - the Anny body model's one-time cache (about a minute, once)
# Offline except the package registries. Idempotent: a second run takes seconds.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
VENV=${ELICIT_VENV:-$ROOT/.venv}
PY=${PYTHON:-python3}
log() { printf '[setup] %s\n' "$*"; }

# 1. System library: libLLVM 19 for drjit/mitsuba's llvm_ad_rgb variant.
if ! ls /usr/lib/*/libLLVM.so.19.1 >/dev/null 2>&1 && ! ls /usr/lib/llvm-19/lib/libLLVM.so.19.1 >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    log "installing libllvm19 (apt)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get install -y -q libllvm19 >/dev/null 2>&1 || { apt-get update -q >/dev/null && apt-get install -y -q libllvm19 >/dev/null; }
  else
    log "libLLVM 19 is missing: run 'apt-get install libllvm19' as root (Mitsuba's llvm variant needs it)"
    exit 1
  fi
fi

# 2. Virtual environment.
if [ ! -x "$VENV/bin/python" ]; then
  log "creating $VENV"
  "$PY" -m venv "$VENV"
  "$VENV/bin/python" -m pip install -q --upgrade pip
fi
PIP=("$VENV/bin/python" -m pip install -q --disable-pip-version-check)

# 3. torch + torchvision that import together (PyPI's torchvision fails beside a mismatched torch).
case "$(uname -m)" in
  aarch64) TORCH_PIN=(torch==2.9.1 torchvision==0.24.1) ;;
  *) TORCH_PIN=(torch==2.14.1 torchvision==0.29.1) ;;
esac
want="${TORCH_PIN[*]}"
have=$("$VENV/bin/python" - <<'EOF' 2>/dev/null || true
import importlib.metadata as m
print(f"torch=={m.version('torch').split('+')[0]} torchvision=={m.version('torchvision').split('+')[0]}")
EOF
)
if [ "$have" != "$want" ]; then
  log "installing ${want}"
  "${PIP[@]}" "${TORCH_PIN[@]}"
fi

# 4. The package and its dev extras, re-run only when pyproject.toml changes.
stamp="$VENV/.elicit-installed"
digest=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$digest" ] || ! "$VENV/bin/python" -c "import elicit_diffrender" 2>/dev/null; then
  log "installing elicit-diffrender[dev]"
  "${PIP[@]}" -e ".[dev]" "${TORCH_PIN[@]}"
  echo "$digest" >"$stamp"
fi

# 5. MediaPipe (masks and keypoints for `elicit prepare`) in its own environment: mediapipe==0.10.21 is
#    the last release whose legacy solutions bundle their models, and it pins numpy<2.
if [ "${ELICIT_NO_MEDIAPIPE:-0}" != 1 ] && [ ! -x "$ROOT/.venv-mediapipe/bin/python" -o ! -f "$ROOT/.venv-mediapipe/.ok" ]; then
  log "creating .venv-mediapipe (mediapipe==0.10.21)"
  "$PY" -m venv "$ROOT/.venv-mediapipe"
  "$ROOT/.venv-mediapipe/bin/python" -m pip install -q --disable-pip-version-check "mediapipe==0.10.21" "numpy<2" pillow
  "$ROOT/.venv-mediapipe/bin/python" -c "import mediapipe" && touch "$ROOT/.venv-mediapipe/.ok"
fi

# 6. Blender as a Python module (bpy 5.0.1, about 1 GB) in its own environment, for the test that opens the
#    exported GLB with Blender's own glTF importer: its wheels exist for Python 3.11 only, and it pins numpy 1.x.
if [ "${ELICIT_NO_BLENDER:-0}" != 1 ] && [ ! -f "$ROOT/.venv-blender/.ok" ]; then
  PY311=$(command -v python3.11 || true)
  [ -z "$PY311" ] && "$PY" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' && PY311=$PY
  if [ -z "$PY311" ]; then
    log "Python 3.11 is missing: bpy (Blender as a module, for the export's Blender test) needs it; set ELICIT_NO_BLENDER=1 to skip"
    exit 1
  fi
  log "creating .venv-blender (bpy==5.0.1)"
  "$PY311" -m venv "$ROOT/.venv-blender"
  "$ROOT/.venv-blender/bin/python" -m pip install -q --disable-pip-version-check "bpy==5.0.1"
  "$ROOT/.venv-blender/bin/python" -c "import bpy" && touch "$ROOT/.venv-blender/.ok"
fi

# 7. Web tools for the glTF export and its viewer page: Node.js, the Khronos glTF validator, three.js and
#    esbuild (npm) in .tools/node; the viewer bundled into .tools/viewer/viewer.js; Chromium (headless) for
#    the page's screenshot test.
NPM_PACKAGES=(gltf-validator@2.0.0-dev.3.10 three@0.187.0 esbuild@0.25.0)
need_apt=()
command -v npm >/dev/null || need_apt+=(nodejs npm)
command -v chromium >/dev/null || need_apt+=(chromium)
if [ ${#need_apt[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    log "installing ${need_apt[*]} (apt)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get install -y -q "${need_apt[@]}" >/dev/null 2>&1 || { apt-get update -q >/dev/null && apt-get install -y -q "${need_apt[@]}" >/dev/null; }
  else
    log "missing ${need_apt[*]}: run 'apt-get install ${need_apt[*]}' as root (the glTF export's checks need them)"
    exit 1
  fi
fi
stamp="$ROOT/.tools/node/.ok-$(echo "${NPM_PACKAGES[*]}" | sha256sum | cut -c1-12)"
if [ ! -f "$stamp" ]; then
  log "installing ${NPM_PACKAGES[*]} (npm) into .tools/node"
  mkdir -p "$ROOT/.tools/node"
  npm install --silent --no-audit --no-fund --prefix "$ROOT/.tools/node" "${NPM_PACKAGES[@]}" >/dev/null
  touch "$stamp"
fi
bundle="$ROOT/.tools/viewer/viewer.js"
if [ ! -f "$bundle" ] || [ "$ROOT/scripts/viewer/viewer.js" -nt "$bundle" ] || [ "$stamp" -nt "$bundle" ]; then
  log "bundling the viewer page's script (esbuild)"
  mkdir -p "$ROOT/.tools/viewer"
  NODE_PATH="$ROOT/.tools/node/node_modules" "$ROOT/.tools/node/node_modules/.bin/esbuild" \
    "$ROOT/scripts/viewer/viewer.js" --bundle --format=iife --minify --log-level=warning --outfile="$bundle"
fi

# 8. Anny builds a cache on first use (about a minute); do it once here, not in the demo or tests.
"$VENV/bin/python" -m elicit_diffrender.body.anny_cache
log "ready: $VENV"
