#!/usr/bin/env bash
# End-to-end timing of `vernier detect`, as a user pays it: each frame is an 8-bit PGM file
# read from disk, decoded, converted and detected (the `time_ms` column covers all of that,
# not the process start). Prints, per case, the first frame of a one-shot run (plan and
# buffer set-up included) and the median of the steady-state frames, with full detection on
# every frame and with `--track` (full search every 30 frames), on 1 thread (`taskset -c 0`:
# the detector uses the cores the process may run on) and on every core. Each case repeats one
# frame, except the real HP sequence (`Image96`-`Image125`, each frame once: a first frame
# there is that run's frame 0).
#
#   bash scripts/bench_end_to_end.sh [FRAMES]     (default 30 frames per case)
#
# VERNIER_BIN (default target/release/vernier) picks the binary; BASELINE_BIN, when set, adds
# that binary's median in the same run (interleaved, case by case) and the ratio, so that two
# builds are compared on a noisy machine.
#
# Needs the release CLI (`cargo build --release -p vernier-cli`), the test tools' Pillow (for
# the PGM files: `bash scripts/setup_test_tools.sh`) and `../shared/data` (or VERNIER_DATA_DIR).
# Not run in CI: it times.
set -euo pipefail
cd "$(dirname "$0")/.."
frames=${1:-30}
data=${VERNIER_DATA_DIR:-../shared/data}
vernier=${VERNIER_BIN:-target/release/vernier}
baseline=${BASELINE_BIN:-}
for need in "$vernier" ${baseline:+"$baseline"} "$data/hpcode/Image100.png" \
    "$data/stamp/stampPatternImage_15um.jpg"; do
    [ -e "$need" ] || { echo "bench_end_to_end: missing $need" >&2; exit 1; }
done
python=.venv/bin/python
"$python" -c "import PIL" 2>/dev/null ||
    { echo "bench_end_to_end: needs Pillow: bash scripts/setup_test_tools.sh" >&2; exit 1; }
command -v taskset >/dev/null || { echo "bench_end_to_end: needs taskset (util-linux)" >&2; exit 1; }
cores=$(nproc)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

# Synthetic frames like the library benches: period 10 px, 1 % noise.
cat >"$work/periodic.json" <<'JSON'
{"PeriodicPattern": {"unit": "um", "period": 10.0, "nRows": 113, "nCols": 113}}
JSON
cat >"$work/megarena.json" <<'JSON'
{"MegarenaPattern": {"unit": "um", "codeDepth": 12, "period": 10.0}}
JSON
"$vernier" render --pattern "$work/periodic.json" --pose 1.2,-3.4,0.3 --pixel-size 1 \
    --size 512x512 --noise 0.01 "$work/periodic.png"
"$vernier" render --pattern "$work/megarena.json" --pose=-51234.5,-43210.9,0.4 --pixel-size 1 \
    --size 1024x1024 --noise 0.01 "$work/megarena.png"
# SOURCE DEST [LEFT TOP SIZE]: an 8-bit grey PGM of SOURCE (a SIZE² crop at LEFT, TOP).
to_pgm() {
    "$python" - "$@" <<'PY'
import sys
from PIL import Image
source, dest, *crop = sys.argv[1:]
image = Image.open(source)
if image.mode in ("I", "I;16", "I;16B"):
    image = image.point(lambda v: v / 257)
image = image.convert("L")
if crop:
    left, top, size = map(int, crop)
    image = image.crop((left, top, left + size, top + size))
image.save(dest)
PY
}
to_pgm "$data/hpcode/Image100.png" "$work/hp_full.pgm"
to_pgm "$data/hpcode/Image100.png" "$work/hp_crop.pgm" 468 454 1024
to_pgm "$data/stamp/stampPatternImage_15um.jpg" "$work/stamp.pgm"
to_pgm "$work/periodic.png" "$work/periodic.pgm"
to_pgm "$work/megarena.png" "$work/megarena.pgm"

# BINARY CPUS FLAGS... FILES...: `time_ms` of frame 0 and the median of the others, one
# image at a time (`--jobs 1`: a frame's latency; independent images otherwise run several at
# once, see the throughput lines).
timed() {
    local binary=$1 cpus=$2
    shift 2
    local jobs=()
    [ "$binary" = "$vernier" ] && jobs=(--jobs 1)
    taskset -c "$cpus" "$binary" detect "${jobs[@]}" "$@" --format csv 2>/dev/null | python3 -c '
import csv, statistics, sys
times = {}
for row in csv.DictReader(sys.stdin):
    times[int(row["frame"])] = float(row["time_ms"])
steady = [t for f, t in times.items() if f > 0]
print(f"{times[0]:.1f} {statistics.median(steady):.1f}")
'
}

# One table row: NAME ORIGINAL MODE THREADS FIRST FILES..., with the flags in `flags`; FIRST
# "-" takes the run's own frame 0 (a sequence: the first frame of the same run).
row() {
    local name=$1 original=$2 mode=$3 threads=$4 first=$5
    shift 5
    local extra=() cpus="0-$((threads - 1))" frame0 steady base="" ratio=""
    [ "$mode" = track ] && extra=(--track)
    read -r frame0 steady < <(timed "$vernier" "$cpus" "${flags[@]}" "${extra[@]}" "$@")
    [ "$first" = - ] && first=$frame0
    if [ -n "$baseline" ]; then
        read -r _ base < <(timed "$baseline" "$cpus" "${flags[@]}" "${extra[@]}" "$@")
        ratio=$(python3 -c "print(f'{$base / $steady:.2f}x')")
    fi
    local speedup
    speedup=$(python3 -c "print(f'{float(\"$original\") / $steady:.0f}x')")
    echo "| $name | $mode | $threads | $first | $steady | $original | $speedup |${baseline:+ $base | $ratio |}"
}

# One case, FILE repeated: NAME, FILE, ORIGINAL (ms, the original measured on this kind of
# machine), flags.
run_case() {
    local name=$1 file=$2 original=$3
    shift 3
    flags=("$@")
    local list=()
    for i in $(seq "$frames"); do
        ln -sf "$file" "$work/frame_$i.pgm"
        list+=("$work/frame_$i.pgm")
    done
    for mode in full track; do
        for threads in 1 "$cores"; do
            # One-shot first frame: a fresh process on one file.
            local first
            read -r first _ < <(timed "$vernier" "0-$((threads - 1))" "$@" "$file" "$file")
            row "$name" "$original" "$mode" "$threads" "$first" "${list[@]}"
        done
    done
}

# One case on the frames in `sequence`, each once: NAME, ORIGINAL (ms), flags.
run_sequence_case() {
    local name=$1 original=$2
    shift 2
    flags=("$@")
    [ "${#sequence[@]}" -gt 2 ] || { echo "| $name | (frames missing) |"; return; }
    for mode in full track; do
        for threads in 1 "$cores"; do
            row "$name" "$original" "$mode" "$threads" - "${sequence[@]}"
        done
    done
}

header="| case | mode | threads | first frame ms | steady frame ms (median) | original ms | speed-up |"
rule="|---|---|---|---|---|---|---|"
if [ -n "$baseline" ]; then
    header="$header baseline ms | baseline / this |"
    rule="$rule---|---|"
fi
echo "$header"
echo "$rule"
# The original's times: its `compute()` (FFTW, -O3, OpenMP) on this kind of 2-core machine,
# from the same 8-bit PGM frames (docs/benchmarks.md).
run_case "HP code 2456x2054" "$work/hp_full.pgm" 84 --hpcode --period 15.5 --code-size 33
run_case "HP code 1024² crop" "$work/hp_crop.pgm" 58 --hpcode --period 15.5 --code-size 33
# The real sequence (Image96-Image125, 30 frames of a moving part): a repeated frame is the
# tracked fit's best case (its first sweep starts where the last converged, with no new noise).
sequence=()
for i in $(seq 96 125); do
    [ -e "$data/hpcode/Image$i.png" ] || continue
    to_pgm "$data/hpcode/Image$i.png" "$work/seq_$i.pgm"
    sequence+=("$work/seq_$i.pgm")
done
run_sequence_case "HP code 2456x2054, real sequence" 84 --hpcode --period 15.5 --code-size 33
run_case "Periodic 512²" "$work/periodic.pgm" 25.5 --pattern "$work/periodic.json"
run_case "Megarena 1024²" "$work/megarena.pgm" 182 --pattern "$work/megarena.json"
run_case "Stamp 1655x762" "$work/stamp.pgm" 239 --stamp --period 15 \
    --bitmap "$data/layouts/stamp69x69.png"

# Throughput of a batch of independent frames (no --track) on every core: wall time of the
# whole run (process start included) over its frames, default `--jobs` (one image per core)
# against `--jobs 1` (one image at a time, its markers spread over the cores).
echo
echo "| batch of $frames independent 5 MP HP frames, $cores cores | wall ms per frame |"
echo "|---|---|"
list=()
for i in $(seq "$frames"); do
    ln -sf "$work/hp_full.pgm" "$work/frame_$i.pgm"
    list+=("$work/frame_$i.pgm")
done
for jobs in 1 0; do
    start=$(date +%s.%N)
    "$vernier" detect --jobs "$jobs" --hpcode --period 15.5 --code-size 33 --format csv \
        "${list[@]}" >/dev/null 2>&1
    end=$(date +%s.%N)
    label=$([ "$jobs" = 0 ] && echo "--jobs 0 (one image per core)" || echo "--jobs 1")
    echo "| $label | $(python3 -c "print(f'{($end - $start) * 1e3 / $frames:.1f}')") |"
done
