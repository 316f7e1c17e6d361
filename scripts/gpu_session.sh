#!/usr/bin/env bash
# One call on a lent GPU machine (the device tool's `run`, from the repo root): the CUDA tests, then a
# time-boxed demo of a preset trained on the GPU (its schedule sized to the time box, so a cosine
# schedule ends where it should), then its evaluation; what the team needs comes back under $OUT (the demo
# folder as demo.tar.gz, or demo.tar.gz.part-aa, -ab, … when over 15 MiB: scripts/pack_demo.sh).
#
#   bash scripts/gpu_session.sh                          # quick preset, 6 minutes of training
#   PRESET=paper-unrolled MINUTES=7 TESTS=0 bash scripts/gpu_session.sh
#   SETS="data.synthetic_n=256 data.val_pool=64" bash scripts/gpu_session.sh   # more scenes, same validation
#
# Environment: PRESET (default quick), MINUTES of training (default 6; the calibration, data generation
# and evaluation come on top: keep MINUTES + 3 within the call's limit), SETS (extra KEY=VALUE
# overrides, space-separated), TESTS (1: run the `cuda`-marked tests first), CALIB_PATCHES (patches per
# epoch of the 2 calibration epochs; default the preset's: a paper-scale epoch of 1890 patches is too long
# to spend on timing), BUDGET (train.max_minutes as a multiple of MINUTES, default 1.5), DEVICE (default cuda;
# `PYTHON=.venv/bin/python DEVICE=cpu PRESET=tiny MINUTES=0.2` tries the script here), OUT (the device tool's $OUT; elsewhere default a temporary folder, printed),
# WORKERS (DataLoader workers, default 8 on CUDA, 0 on CPU).
# The device image has python3 with a CUDA torch and most dependencies; colour-science (to generate the
# synthetic data) and openexr / gdstk (some tests) travel as wheels in .whl: fetch them here first with
# `bash scripts/gpu_session.sh --fetch-wheels`, and name .whl in the run's carry.
set -euo pipefail

WHEELS="colour-science==0.4.7 openexr==3.5.3 gdstk==1.0.2"
if [[ "${1:-}" == "--fetch-wheels" ]]; then
    mkdir -p .git/info && { grep -qx "/.whl/" .git/info/exclude 2>/dev/null || echo "/.whl/" >> .git/info/exclude; }
    PY=${PYTHON:-.venv/bin/python}
    # shellcheck disable=SC2086
    "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_24_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 -d .whl $WHEELS
    ls -la .whl
    exit 0
fi

PRESET=${PRESET:-quick}
MINUTES=${MINUTES:-6}
SETS=${SETS:-}
TESTS=${TESTS:-1}
DEVICE=${DEVICE:-cuda}
if [[ "$DEVICE" == cpu ]]; then WORKERS=${WORKERS:-0}; else WORKERS=${WORKERS:-8}; fi
PY=${PYTHON:-python3}
if ! "$PY" -c "import torch" 2>/dev/null; then  # else set -e stopped the env.txt block below, its error only in env.txt
    echo "gpu_session.sh: $PY cannot import torch; set PYTHON to the project's python (e.g. PYTHON=.venv/bin/python)" >&2
    exit 1
fi

WORK=$(mktemp -d "${TMPDIR:-/tmp}/hsicam-gpu.XXXXXX")
OUT=${OUT:-$WORK/out}
echo "work folder $WORK, results in $OUT"
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 HSICAM_CACHE="$WORK/cache"

if compgen -G ".whl/*.whl" > /dev/null && ! "$PY" -c "import colour, gdstk, OpenEXR" 2>/dev/null; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$WORK/site" .whl/*.whl
    export PYTHONPATH="$PWD/src:$WORK/site${PYTHONPATH:+:$PYTHONPATH}"
else
    export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
fi

{
    date -u
    nvidia-smi 2>/dev/null || echo "no nvidia-smi"
    "$PY" -c "import torch, sys; print('python', sys.version.split()[0], 'torch', torch.__version__, 'cuda', torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else '')"
    echo "PRESET=$PRESET MINUTES=$MINUTES DEVICE=$DEVICE WORKERS=$WORKERS SETS=$SETS"
    git log -1 --format='commit %H %s' 2>/dev/null || true
} > "$OUT/env.txt" 2>&1
cat "$OUT/env.txt"

if [[ "$TESTS" == 1 ]]; then
    echo "== cuda tests"
    # the tests marked cuda (and nothing slow); their log comes back whatever they say
    timeout 240 "$PY" -m pytest -q -p no:cacheprovider -m "cuda and not slow" tests > "$OUT/cuda_tests.log" 2>&1 \
        || echo "cuda tests: exit $? (see cuda_tests.log)"
    tail -n 3 "$OUT/cuda_tests.log"
fi

overrides=(--set "train.device=$DEVICE" --set "data.num_workers=$WORKERS")
for kv in $SETS; do overrides+=(--set "$kv"); done

echo "== calibration: 2 epochs of $PRESET (also generates the data)"
# every step logged (the presets log every 20th): the step time is read off consecutive steps
calib=(--set train.epochs=2 --set train.log_every_steps=1)
if [[ -n "${CALIB_PATCHES:-}" ]]; then calib+=(--set "data.patches_per_epoch=$CALIB_PATCHES"); fi
"$PY" -m hsicam train --config "$PRESET" --out "$WORK/calib" "${overrides[@]}" "${calib[@]}" \
    > "$WORK/calib.log" 2>&1 || { tail -n 20 "$WORK/calib.log"; cp "$WORK/calib.log" "$OUT/"; exit 1; }
EPOCHS=$("$PY" "$(dirname "$0")/calibrate_epochs.py" "$WORK/calib/metrics.jsonl" "$MINUTES" "$PRESET" "${overrides[@]}")
echo "epochs: $EPOCHS"

echo "== demo: $PRESET, $EPOCHS epochs (budget $MINUTES min × ${BUDGET:-1.5})"
budget=$("$PY" -c "print(round(float('$MINUTES') * float('${BUDGET:-1.5}'), 2))")
status=0
"$PY" -m hsicam demo --config "$PRESET" --out "$WORK/demo" "${overrides[@]}" --set "train.epochs=$EPOCHS" \
    --set "train.max_minutes=$budget" > "$OUT/demo.log" 2>&1 || status=$?
tail -n 30 "$OUT/demo.log"
if [[ $status == 75 && -d "$WORK/demo/run" ]]; then
    # the time budget stopped it (the calibration was optimistic): score the partly trained run anyway
    echo "demo: stopped by the time budget; evaluating the partly trained run into eval-partial/"
    "$PY" -m hsicam evaluate --run "$WORK/demo/run" --out "$WORK/demo/eval-partial" > "$OUT/eval-partial.log" 2>&1 \
        || echo "evaluate: exit $? (see eval-partial.log)"
    tail -n 5 "$OUT/eval-partial.log"
elif [[ $status != 0 ]]; then
    echo "demo: exit $status"
fi

# at most 8 files come back: the figures, tables and weights in one archive (in 15 MiB parts when larger)
if [[ -d "$WORK/demo" ]]; then
    bash "$(dirname "$0")/pack_demo.sh" "$WORK/demo" "$OUT/demo.tar.gz"
    ls -la "$OUT"
fi
exit $status
