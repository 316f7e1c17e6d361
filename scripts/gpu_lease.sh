#!/usr/bin/env bash
# One call on a lent GPU machine that makes its minutes count twice: two time-boxed demos side by side on
# the one GPU (`scripts/gpu_session.sh` each; a small network leaves most of an H200 idle), and meanwhile
# the CUDA tests and a CUDA smoke training of the tiny preset with bf16, channels_last and torch.compile.
# Every training ends within LIMIT seconds (coreutils `timeout`; a stopped training saves its step), so
# the archives are packed inside the call's own limit. What comes back under $OUT (6 files; 8 when both demo
# archives are over 15 MiB and come in two parts, a_demo.tar.gz.part-aa and -ab: scripts/pack_demo.sh):
#   a.log, b.log       each demo's session log (calibration, epochs chosen, the demo's last lines)
#   a_demo.tar.gz, b_demo.tar.gz   each demo folder (figures, tables, results.json; weights when small; a demo
#                      that LIMIT stopped: its folder as it was, the run's config and metrics.jsonl in it)
#   gpu_checks.log     the CUDA tests and the smoke training
#   logs.tar.gz        every log (calibration, demo, evaluation) of both
#
#   A_PRESET=paper-unrolled A_MINUTES=4.5 B_PRESET=quick B_MINUTES=4.5 \
#   B_SETS="data.synthetic_n=256 data.val_pool=64" bash scripts/gpu_lease.sh
#
# Environment: A_PRESET, A_MINUTES, A_SETS, A_CALIB_PATCHES, A_WORKERS and the same for B (see gpu_session.sh),
# THREADS_EACH and WORKERS_EACH (each demo's torch threads and DataLoader workers; default (cores − 2) / 4 each,
# so that the two demos' main processes and their workers fill the machine without oversubscribing it),
# LIMIT (seconds for each demo, default 500), BUDGET (default 1.15), DEVICE (default cuda; `DEVICE=cpu
# A_PRESET=tiny B_PRESET=tiny A_MINUTES=0.1 B_MINUTES=0.1` tries it here), OUT (default a temporary folder).
# Wheels: as for gpu_session.sh (`bash scripts/gpu_session.sh --fetch-wheels`, carry .whl).
set -uo pipefail

PY=${PYTHON:-python3}
DEVICE=${DEVICE:-cuda}
LIMIT=${LIMIT:-500}
W=$(mktemp -d "${TMPDIR:-/tmp}/hsicam-lease.XXXXXX")
OUT=${OUT:-$W/out}
mkdir -p "$OUT"
echo "work folder $W, results in $OUT"
export PYTHONUNBUFFERED=1
# The cores shared out: each process's torch (OpenMP) pool sized to its share, since pools that each take every
# core spin against one another (session 49's first lease: two demos and the checks with 16 threads each on 16
# cores; the quick demo's linear-step fit took 144 s for 248 scenes, 2-3 s for 56 on a 2-core CPU alone).
CORES=$(nproc)
THREADS_EACH=${THREADS_EACH:-$(( (CORES - 2) / 4 > 1 ? (CORES - 2) / 4 : 1 ))}
WORKERS_EACH=${WORKERS_EACH:-$(( (CORES - 2) / 4 > 1 ? (CORES - 2) / 4 : 0 ))}
echo "$CORES cores: $THREADS_EACH threads and $WORKERS_EACH DataLoader workers for each demo, 2 threads for the checks"
if compgen -G ".whl/*.whl" > /dev/null && ! "$PY" -c "import colour, gdstk, OpenEXR" 2>/dev/null; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$W/site" .whl/*.whl
    export PYTHONPATH="$W/site${PYTHONPATH:+:$PYTHONPATH}"
fi

demo() {  # demo NAME: one gpu_session.sh run from the NAME_* variables
    local n=$1 p=${1^^} preset minutes sets calib workers
    local v_preset=${p}_PRESET v_minutes=${p}_MINUTES v_sets=${p}_SETS v_calib=${p}_CALIB_PATCHES v_workers=${p}_WORKERS
    preset=${!v_preset:-quick}
    minutes=${!v_minutes:-4}
    sets=${!v_sets:-}
    calib=${!v_calib:-}
    workers=${!v_workers:-$WORKERS_EACH}
    mkdir -p "$W/$n-tmp"
    OUT="$W/$n" PRESET="$preset" MINUTES="$minutes" SETS="$sets" CALIB_PATCHES="$calib" TESTS=0 \
        BUDGET="${BUDGET:-1.15}" DEVICE="$DEVICE" WORKERS="$workers" TMPDIR="$W/$n-tmp" \
        OMP_NUM_THREADS="$THREADS_EACH" MKL_NUM_THREADS="$THREADS_EACH" \
        timeout -k 20 "$LIMIT" bash scripts/gpu_session.sh > "$W/$n.log" 2>&1
    local status=$?
    # timeout ends gpu_session.sh at once, but the training it started saves its step on SIGTERM first (orphaned by
    # then): wait for it, at most a minute, so that its folder is packed whole
    for _ in $(seq 60); do
        pgrep -f -- "$W/$n-tmp" > /dev/null 2>&1 || break
        sleep 1
    done
    echo "gpu_session.sh $n ($preset): exit $status" >> "$W/$n.log"
    if ! compgen -G "$W/$n/demo.tar.gz*" > /dev/null; then
        # stopped before it packed (LIMIT, or a failure): what the demo folder holds so far comes back instead (its
        # run's config, metrics.jsonl and weights, any figures), without checkpoints or data
        local demo_dir
        demo_dir=$(compgen -G "$W/$n-tmp/hsicam-gpu.*/demo" | head -n 1)
        if [[ -n "$demo_dir" ]]; then
            bash scripts/pack_demo.sh "$demo_dir" "$W/$n/demo.tar.gz" >> "$W/$n.log" 2>&1
            echo "packed the demo folder as it was at the stop (exit $status)" >> "$W/$n.log"
        fi
    fi
}

checks() {  # the CUDA tests, then a smoke training of the tiny preset through the CUDA-only options
    export OMP_NUM_THREADS=2 MKL_NUM_THREADS=2
    {
        nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1 || true
        echo "== CUDA tests"
        PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" timeout 200 "$PY" -m pytest -q -p no:cacheprovider -rs \
            "tests/cameras/test_camera_contract.py::test_cpu_equals_cuda" "tests/cameras/test_camera.py::test_cpu_and_cuda_agree" 2>&1 \
            | tail -n 25
        echo "== tiny preset on $DEVICE with bf16, channels_last, compile"
        PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" HSICAM_CACHE="$W/cache-smoke" timeout 200 "$PY" -m hsicam train \
            --config tiny --out "$W/smoke" --set "train.device=$DEVICE" --set train.bf16=true \
            --set train.channels_last=true --set train.compile=true --set train.epochs=3 2>&1 | tail -n 15
        echo "smoke training: exit ${PIPESTATUS[0]}"
    } > "$W/gpu_checks.log" 2>&1
}

checks &
demo a &
demo b &
wait

for n in a b; do
    cp "$W/$n.log" "$OUT/$n.log" 2>/dev/null
    for f in "$W/$n"/demo.tar.gz*; do  # demo.tar.gz, or its 15 MiB parts demo.tar.gz.part-aa, -ab, …
        [[ -f "$f" ]] && cp "$f" "$OUT/${n}_$(basename "$f")"
    done
done
cp "$W/gpu_checks.log" "$OUT/"
(cd "$W" && tar -czf "$OUT/logs.tar.gz" --ignore-failed-read ./*.log ./a/*.log ./b/*.log ./a/env.txt ./b/env.txt \
    ./*-tmp/hsicam-gpu.*/calib.log 2>/dev/null)
if (( $(find "$OUT" -type f | wc -l) > 8 )); then  # the device tool brings back 8 files at most
    echo "warning: $(find "$OUT" -type f | wc -l) files under \$OUT, over the 8 that come back" >&2
fi
ls -la "$OUT"
tail -n 4 "$OUT/gpu_checks.log" "$OUT/a.log" "$OUT/b.log"
