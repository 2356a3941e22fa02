#!/usr/bin/env bash
# GPU benchmark of ggpt-rs on wgpu: one script, one log (docs/performance.md, "wgpu").
#
#   scripts/gpu_bench.sh                    build (release, --features wgpu) and run everything
#   scripts/gpu_bench.sh --quick            small sizes: checks the script itself (lavapipe, CI box)
#   scripts/gpu_bench.sh --prepare DIR      build only; write the binaries, stripped and
#                                           xz-compressed (~11 MB each), into DIR
#   scripts/gpu_bench.sh --bin DIR          run the binaries of DIR, plain or .xz (a GPU machine
#                                           without Rust)
#
# Options: --features LIST (cargo features, default "wgpu"; e.g. "wgpu,fusion,autotune"),
#          --profile NAME (cargo profile, default release), --log FILE (default
#          gpu_bench_<date>.log in the current folder), --device NAME (default wgpu).
# Environment: GGPT_FIXTURES (the fixtures folder; default ../shared/fixtures or
#          shared/fixtures beside the repository), VK_DRIVER_FILES (the Vulkan ICD; set to the
#          NVIDIA one when found), GGPT_STEP_TIMEOUT_S (per step, default 600).
#
# Steps (full / --quick):
#   1. forward      bench forward, released config, 26k / 100k / 400k tokens (quick: 2k, 4k),
#                   two runs each (the second is warm), kernel launches and readbacks counted
#   2. parity       the fixture parity tests with GGPT_TEST_DEVICE=wgpu (tolerance 1e-4), and
#                   the wgpu-vs-ndarray backend test (forward, gradients, recomputed gradients;
#                   optional with --bin: skipped when DIR has no `backends`)
#   3. infer        bench infer --views 4,8,16, released config (quick: --views 2, tiny, <= 60k tokens per forward)
#   4. train        bench train, released config, 10k and 100k tokens, batch 1 (quick: small, 2k)
# The Vulkan loader: when `ldconfig -p` has no libvulkan and `.gl/*.deb` exist in the repository
# (downloaded as /work/.library/device/README.md says), they are unpacked first.
set -uo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
QUICK=0
PREPARE=""
BIN=""
FEATURES="wgpu"
PROFILE="release"
DEVICE="wgpu"
LOG="gpu_bench_$(date -u +%Y%m%dT%H%M%SZ).log"
STEP_TIMEOUT="${GGPT_STEP_TIMEOUT_S:-600}"

usage() { sed -n '2,30p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'; }

while [ $# -gt 0 ]; do
  case "$1" in
    --quick) QUICK=1 ;;
    --prepare) PREPARE="${2:?--prepare needs a folder}"; shift ;;
    --bin) BIN="${2:?--bin needs a folder}"; shift ;;
    --features) FEATURES="${2:?--features needs a list}"; shift ;;
    --profile) PROFILE="${2:?--profile needs a name}"; shift ;;
    --log) LOG="${2:?--log needs a file}"; shift ;;
    --device) DEVICE="${2:?--device needs a name}"; shift ;;
    -h|--help) usage; exit 0 ;;
    *) echo "gpu_bench.sh: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
  shift
done
if [ -n "$PREPARE" ] && [ -n "$BIN" ]; then
  echo "gpu_bench.sh: --prepare and --bin exclude each other" >&2; exit 2
fi

log() { echo "$*" | tee -a "$LOG"; }
T_START=$(date +%s)

# --- Vulkan loader and driver -------------------------------------------------------------
setup_vulkan() {
  # (no `grep -q`: with pipefail, ldconfig's SIGPIPE would read as "not found")
  if ! ldconfig -p 2>/dev/null | grep 'libvulkan\.so\.1' >/dev/null; then
    if compgen -G "$ROOT/.gl/*.deb" >/dev/null; then
      log "# no libvulkan: unpacking $ROOT/.gl/*.deb"
      for f in "$ROOT"/.gl/*.deb; do dpkg -x "$f" / || log "# dpkg -x $f failed"; done
      ldconfig || true
    else
      log "# warning: no libvulkan.so.1 found and no .gl/*.deb to unpack; wgpu will find no adapter"
    fi
  fi
  local icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
  if [ -z "${VK_DRIVER_FILES:-}" ] && [ -f "$icd" ]; then
    export VK_DRIVER_FILES="$icd"
    local egl=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
    [ -f "$egl" ] && export __EGL_VENDOR_LIBRARY_FILENAMES="$egl"
  fi
  if [ -z "${XDG_RUNTIME_DIR:-}" ]; then
    XDG_RUNTIME_DIR="$(mktemp -d)"; export XDG_RUNTIME_DIR
  fi
}

# --- Build: the five binaries, by name -----------------------------------------------------
declare -A EXE
collect_executables() { # reads cargo's JSON messages on stdin; prints "name path" lines
  python3 -c '
import json, sys
for line in sys.stdin:
    try:
        m = json.loads(line)
    except ValueError:
        continue
    if m.get("reason") == "compiler-artifact" and m.get("executable"):
        print(m["target"]["name"], m["executable"])
'
}

build() {
  command -v cargo >/dev/null || { log "# cargo not found: build elsewhere with --prepare DIR, run here with --bin DIR"; exit 2; }
  log "# build: profile $PROFILE, features $FEATURES"
  local t0; t0=$(date +%s)
  local out
  out=$(cd "$ROOT" && cargo bench --profile "$PROFILE" --no-run --locked --features "$FEATURES" \
          -p ggpt-model --bench forward -p ggpt-infer --bench infer -p ggpt-train --bench train \
          --message-format=json 2>>"$LOG" | collect_executables) || { log "# build failed (see above)"; exit 1; }
  while read -r name path; do EXE[$name]="$path"; done <<<"$out"
  out=$(cd "$ROOT" && cargo test --profile "$PROFILE" --no-run --locked --features "$FEATURES" \
          -p ggpt-model --test parity --test backends \
          --message-format=json 2>>"$LOG" | collect_executables) || { log "# test build failed (see above)"; exit 1; }
  while read -r name path; do EXE[$name]="$path"; done <<<"$out"
  log "# build: $(( $(date +%s) - t0 )) s"
  for name in forward infer train parity backends; do
    [ -n "${EXE[$name]:-}" ] || { log "# build produced no '$name' binary"; exit 1; }
  done
}

# --- Run ------------------------------------------------------------------------------------
FAILED=()
step() { # step NAME CMD...: runs CMD with the step timeout, everything into the log
  local name="$1"; shift
  log ""
  log "## $name: $*"
  local t0; t0=$(date +%s)
  timeout "$STEP_TIMEOUT" "$@" 2>&1 | tee -a "$LOG"
  local rc=${PIPESTATUS[0]}
  log "## $name: exit $rc after $(( $(date +%s) - t0 )) s"
  [ "$rc" -eq 0 ] || FAILED+=("$name (exit $rc)")
}

find_fixtures() {
  if [ -n "${GGPT_FIXTURES:-}" ]; then return; fi
  for d in "$ROOT/../shared/fixtures" "$ROOT/shared/fixtures"; do
    if [ -d "$d/ggpt_small" ]; then GGPT_FIXTURES="$(cd "$d" && pwd)"; export GGPT_FIXTURES; return; fi
  done
}

if [ -n "$BIN" ]; then
  UNPACK="$(mktemp -d)"
  for name in forward infer train parity backends; do
    if [ -x "$BIN/$name" ]; then
      EXE[$name]="$BIN/$name"
    elif [ -f "$BIN/$name.xz" ]; then
      xz -d -c "$BIN/$name.xz" >"$UNPACK/$name" && chmod +x "$UNPACK/$name" \
        || { echo "gpu_bench.sh: cannot unpack $BIN/$name.xz" >&2; exit 2; }
      EXE[$name]="$UNPACK/$name"
    elif [ "$name" != backends ]; then
      echo "gpu_bench.sh: $BIN/$name(.xz) is missing (make it with --prepare)" >&2; exit 2
    fi
  done
else
  : >>"$LOG"
  build
  if [ -n "$PREPARE" ]; then
    mkdir -p "$PREPARE"
    for name in forward infer train parity backends; do
      cp "${EXE[$name]}" "$PREPARE/$name.tmp" || exit 1
      strip "$PREPARE/$name.tmp" 2>/dev/null || true
      xz -T0 -6 -c "$PREPARE/$name.tmp" >"$PREPARE/$name.xz.tmp" && mv "$PREPARE/$name.xz.tmp" "$PREPARE/$name.xz" \
        || { log "# xz of $name failed"; exit 1; }
      rm -f "$PREPARE/$name.tmp"
    done
    log "# prepared: $(du -sh "$PREPARE" | cut -f1) in $PREPARE (run there: scripts/gpu_bench.sh --bin $PREPARE)"
    exit 0
  fi
fi

setup_vulkan
find_fixtures
[ -n "$BIN" ] && FEATURES="as built into $BIN"
log "# gpu_bench.sh $(date -u +%FT%TZ) quick=$QUICK device=$DEVICE features: $FEATURES"
log "# git $(cd "$ROOT" && git rev-parse --short HEAD 2>/dev/null || echo unknown)"
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>&1 | sed 's/^/# gpu: /' | tee -a "$LOG"
log "# cpu: $(nproc) cores; VK_DRIVER_FILES=${VK_DRIVER_FILES:-unset}; GGPT_FIXTURES=${GGPT_FIXTURES:-not found}"

if [ "$QUICK" -eq 1 ]; then
  # (smaller scenes make the official chunk sampler reject every chunk; forwards of <= 60k
  # tokens stay under lavapipe's buffer limit)
  FWD_TOKENS=2000,4000; INFER_ARGS=(--views 2 --preset tiny --max-tokens-per-forward 60000)
  TRAIN_ARGS=(--config small --tokens 2000 --batch 1 --steps 1)
else
  FWD_TOKENS=26000,100000,400000; INFER_ARGS=(--views 4,8,16)
  TRAIN_ARGS=(--config released --tokens 10000,100000 --batch 1 --steps 2)
fi

step forward "${EXE[forward]}" --device "$DEVICE" --tokens "$FWD_TOKENS" --repeat 2 --count
if [ -n "${GGPT_FIXTURES:-}" ]; then
  step parity env GGPT_TEST_DEVICE="$DEVICE" "${EXE[parity]}" --test-threads 1
  if [ -n "${EXE[backends]:-}" ]; then
    step backends "${EXE[backends]}" wgpu_agrees_with_ndarray --test-threads 1
  fi
else
  log "## parity: SKIPPED, no fixtures (set GGPT_FIXTURES to the shared/fixtures folder)"
  FAILED+=("parity (no fixtures)")
fi
step infer "${EXE[infer]}" --device "$DEVICE" "${INFER_ARGS[@]}"
# a scene whose chunks were all rejected measures nothing: say so
if sed -n '/^## infer: /,/^## infer: exit/p' "$LOG" | grep -q ' 0 forwards run'; then
  log "## infer: a scene ran no chunk through the network"
  FAILED+=("infer (no chunk refined)")
fi
step train "${EXE[train]}" --device "$DEVICE" "${TRAIN_ARGS[@]}"

log ""
log "# total $(( $(date +%s) - T_START )) s; log: $LOG"
if [ ${#FAILED[@]} -gt 0 ]; then
  log "# FAILED: ${FAILED[*]}"
  exit 1
fi
log "# all steps passed"
