#!/usr/bin/env bash
# End-to-end timing of `vernier detect`, as a user pays it: each frame is an 8-bit PGM file
# read from disk, decoded, converted and detected (the `time_ms` column covers all of that,
# not the process start). Prints, per case, the first frame (plan and buffer set-up
# included) and the median of the steady-state frames, with full detection on every frame
# and with `--track` (full search every 30 frames).
#
#   bash scripts/bench_end_to_end.sh [FRAMES]     (default 30 frames per case)
#
# Needs the release CLI (`cargo build --release -p vernier-cli`), the test tools' Pillow (for
# the PGM files: `bash scripts/setup_test_tools.sh`) and `../shared/data` (or VERNIER_DATA_DIR).
# Not run in CI: it times.
set -euo pipefail
cd "$(dirname "$0")/.."
frames=${1:-30}
data=${VERNIER_DATA_DIR:-../shared/data}
vernier=target/release/vernier
for need in "$vernier" "$data/hpcode/Image100.png" "$data/stamp/stampPatternImage_15um.jpg"; do
    [ -e "$need" ] || { echo "bench_end_to_end: missing $need" >&2; exit 1; }
done
python=.venv/bin/python
"$python" -c "import PIL" 2>/dev/null ||
    { echo "bench_end_to_end: needs Pillow: bash scripts/setup_test_tools.sh" >&2; exit 1; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

# Synthetic frames like the library benches: period 10 px, 1 % noise.
cat >"$work/periodic.json" <<'EOF'
{"PeriodicPattern": {"unit": "um", "period": 10.0, "nRows": 113, "nCols": 113}}
EOF
cat >"$work/megarena.json" <<'EOF'
{"MegarenaPattern": {"unit": "um", "codeDepth": 12, "period": 10.0}}
EOF
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

# One case: NAME, FILE, ORIGINAL (ms, from issue 17's side-by-side run), detector flags.
run_case() {
    local name=$1 file=$2 original=$3
    shift 3
    local list=()
    for i in $(seq "$frames"); do
        ln -sf "$file" "$work/frame_$i.pgm"
        list+=("$work/frame_$i.pgm")
    done
    for mode in full track; do
        local extra=()
        [ "$mode" = track ] && extra=(--track)
        "$vernier" detect "$@" "${extra[@]}" --format csv "${list[@]}" 2>/dev/null |
            python3 -c '
import csv, statistics, sys
name, mode, original = sys.argv[1:4]
times, markers = {}, {}
for row in csv.DictReader(sys.stdin):
    f = int(row["frame"])
    times[f] = float(row["time_ms"])
    markers[f] = markers.get(f, 0) + (row["id"] != "")
steady = [t for f, t in times.items() if f > 0]
med = statistics.median(steady)
print(f"| {name} | {mode} | {max(markers.values())} | {times[0]:.1f} | {med:.1f} | {original} | {float(original.split(chr(8211))[0]) / med:.0f}x |")
' "$name" "$mode" "$original"
    done
}

echo "| case | mode | markers | first frame ms | steady frame ms (median) | original ms | speed-up (vs the original's fastest) |"
echo "|---|---|---|---|---|---|---|"
run_case "HP code 2456x2054" "$work/hp_full.pgm" "116–180" --hpcode --period 15.5 --code-size 33
run_case "HP code 1024² crop" "$work/hp_crop.pgm" "75–100" --hpcode --period 15.5 --code-size 33
run_case "Periodic 512²" "$work/periodic.pgm" "32–33" --pattern "$work/periodic.json"
run_case "Megarena 1024²" "$work/megarena.pgm" "180–241" --pattern "$work/megarena.json"
run_case "Stamp 1655x762" "$work/stamp.pgm" "401" --stamp --period 15 \
    --bitmap "$data/layouts/stamp69x69.png"
