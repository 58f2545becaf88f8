#!/usr/bin/env bash
# The CUDA checks in one run, on a machine with an NVIDIA card (docs/benchmarks.md §12): the test
# suite with every fit on the GPU (STATFIT_DEVICE=cuda, pytest-xdist), the files in FIRST before the
# rest, then benchmarks/gpu.py; each under a time limit, so the whole run ends within TOTAL_S seconds
# and what it reached is in OUT_DIR (logs, junit XML, gpu.json).
#
#   TOTAL_S=560 BENCH_S=250 WORKERS=14 bash benchmarks/cuda_check.sh OUT_DIR
#
# On a machine without network (Python 3.12): WHEELS=DIR installs the wheels in DIR, made here by
# benchmarks/cuda_wheels.sh, into a private folder first; ICT=DIR links the ICT-FaceKit files in DIR
# where the tests and benchmarks look for them (../shared/data/ict-face). BENCH_S=0 skips gpu.py;
# DEVICE=cpu runs the same on the CPU (a dry run of this script). PROFILE=1 also writes gpu.py's
# profile of the maps' fits stepped together to OUT_DIR/profile.txt; GPU_ARGS passes gpu.py more
# options (e.g. "--only render"); BENCH_FIRST=1 runs gpu.py first, for its first BENCH_S seconds.
set -uo pipefail
out=${1:?usage: bash benchmarks/cuda_check.sh OUT_DIR}
total=${TOTAL_S:-560}
bench=${BENCH_S:-250}
workers=${WORKERS:-14}
device=${DEVICE:-cuda}
# The files to check first: those that failed at the last card run (session 43, the whole suite;
# six batch tests by torch's lazy CUDA linear-algebra load raced on threads, mended since) and those
# changed since (session 44: the pose search's second look; session 45: the closed form's rigid motion).
# A run cut short by its limit has checked them. A second call on a warm machine is sent a fresh tree:
# run this script again (it links the ICT data) rather than pytest alone.
first=${FIRST:-"tests/test_device.py tests/test_batch.py tests/test_batch_report.py tests/test_batch_landmarks.py
                tests/test_params.py tests/test_cli_render.py tests/test_normalmap_io.py tests/test_pose_refusals.py
                tests/test_pose_second_look.py tests/test_closed_form_pose.py"}
cd "$(dirname "$0")/.."
mkdir -p "$out"
begin=$SECONDS
left() { echo $(( $1 - (SECONDS - begin) )); }

if [ -n "${WHEELS:-}" ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/statfit-site "$WHEELS"/*.whl || exit 2
    export PYTHONPATH=/tmp/statfit-site${PYTHONPATH:+:$PYTHONPATH}
fi
if [ -n "${ICT:-}" ] && [ ! -e ../shared/data/ict-face ]; then
    mkdir -p ../shared/data && ln -s "$(realpath "$ICT")" ../shared/data/ict-face
fi
python3 -c "import statfit" 2>/dev/null ||
    python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . || exit 2
{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
  python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"; } | tee "$out/machine.txt"

export STATFIT_DEVICE=$device PYTHONUNBUFFERED=1
suite() {    # until $1 seconds into the run
    local ignore=() file
    for file in $first; do ignore+=(--ignore "$file"); done
    # shellcheck disable=SC2086
    timeout -s INT -k 30 "$(left "$1")" python3 -m pytest -q -n "$workers" -p no:cacheprovider $first \
        --junitxml "$out/first.xml" > "$out/first.log" 2>&1
    echo "first files: exit $? ($(tail -1 "$out/first.log"))"
    timeout -s INT -k 30 "$(left "$1")" python3 -m pytest -q -n "$workers" -p no:cacheprovider \
        tests "${ignore[@]}" \
        --junitxml "$out/rest.xml" > "$out/rest.log" 2>&1
    echo "the rest: exit $? ($(tail -1 "$out/rest.log"))"
    grep -h "^FAILED\|^ERROR" "$out/first.log" "$out/rest.log" | head -30
    # Session 33's mend of a graph kept across captures: torch's warning of it should be gone.
    echo "AccumulateGrad stream warnings: $(cat "$out"/*.log "$out"/gpu.md 2>/dev/null | grep -c "AccumulateGrad node's stream")"
}
benchmark() {    # until $1 seconds into the run
    local extra=()
    [ -n "${PROFILE:-}" ] && extra+=(--profile "$out/profile.txt")
    # shellcheck disable=SC2206
    extra+=(${GPU_ARGS:-})
    timeout "$(left "$1")" python3 benchmarks/gpu.py --device "$device" --out "$out/gpu.json" "${extra[@]}" \
        > "$out/gpu.md" 2>&1
    echo "gpu.py: exit $?"
    cat "$out/gpu.md"
}
if [ "$bench" -le 0 ]; then
    suite "$total"
elif [ -n "${BENCH_FIRST:-}" ]; then
    benchmark "$bench"
    suite "$total"
else
    suite $((total - bench))
    benchmark "$total"
fi
