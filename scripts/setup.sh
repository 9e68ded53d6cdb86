#!/usr/bin/env bash
# Creates .venv and installs splitbench with everything it needs, including the system
# libraries that pip cannot provide:
#   - libLLVM >= 16 for Dr.Jit's LLVM backend (Debian's default libLLVM-15 aborts in
#     rendering kernels with "LLVM ERROR: Cannot select: ... fmaximum").
#   - liblzo2-dev, so that python-lzo (seed 000's LZO codec) can be built. Optional.
#   - Debian's OpenArena data (maps, textures, shader scripts; GPL-2+) for the oa:<map> scenes
#     (docs/scenes.md). Optional: without it those scenes are listed as unavailable and their tests skip.
# As root on Debian/Ubuntu it installs them with apt-get. Without root it tells you what to do
# (see README "Without root") and stops if no usable libLLVM exists.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=.venv

have_llvm() { "$PY" scripts/find_llvm.py >/dev/null 2>&1; }

if ! have_llvm; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    echo "setup: installing libllvm19 for Dr.Jit (apt-get)"
    apt-get update -qq >/dev/null
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null
  fi
fi
if ! have_llvm; then
  "$PY" scripts/find_llvm.py || true
  exit 2
fi

LZO=""
if [ ! -e /usr/include/lzo/lzo1x.h ] && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
  echo "setup: installing liblzo2-dev for the optional LZO codec (apt-get)"
  (apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq liblzo2-dev >/dev/null) \
    || echo "setup: liblzo2-dev not installable; the LZO codec will be reported as unavailable"
fi
[ -e /usr/include/lzo/lzo1x.h ] && LZO=",lzo"

OA_DIR=/usr/share/games/openarena/baseoa
OA_PACKAGES="openarena-081-maps openarena-088-data openarena-data openarena-081-textures"
have_oa() {
  for pk3 in pak0.pk3 pak1-maps.pk3 pak4-textures.pk3 pak6-patch088.pk3; do [ -e "$OA_DIR/$pk3" ] || return 1; done
}
if ! have_oa && [ -z "${SPLITBENCH_OA_PATH:-}" ] && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
  echo "setup: installing the OpenArena maps and textures for the oa: scenes (apt-get, about 300 MB)"
  (apt-get update -qq >/dev/null \
    && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $OA_PACKAGES >/dev/null) \
    || echo "setup: OpenArena packages not installable; oa: scenes will be listed as unavailable (docs/scenes.md)"
fi

if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q -e ".[test${LZO}]"
"$VENV/bin/python" -c "import suite.core.env as e; e.check_llvm_backend()" 
touch "$VENV/.installed"
echo "setup: ready ($VENV)"
