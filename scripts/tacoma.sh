#!/usr/bin/env bash
# Real footage, no ground truth: the Tacoma Narrows deck (1940) twisting, measured with the
# default method (deepflow, every frame against frame 0) and with the paper's KLT baseline.
#
#   scripts/tacoma.sh [FIG_DIR [DATA_DIR]]   (default results/figures, results/tacoma; ~45 s on 2 cores)
#
# Writes FIG_DIR/tacoma_displacement.png (time histories + spectra, dominant frequency marked)
# and FIG_DIR/tacoma_pois.png (mask POIs vs the Harris corners KLT uses), the CSVs and sidecars
# to DATA_DIR, and prints the dominant frequencies. Then the deck at four places in one run
# (a labelled mask: the near curb in three pieces and the far deck edge against the sky):
# FIG_DIR/tacoma_regions.png (each region's history and spectrum) and tacoma_regions_pois.png;
# DATA_DIR/regions.csv is the defaults' result, regions_kept.csv the readings the figure shows.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
clip=${TACOMA_CLIP:-$root/../shared/data/tacoma_bridge.mp4}
out=${1:-$root/results/figures}
data=${2:-$root/results/tacoma}
refflow=${REFFLOW:-$root/.venv/bin/refflow}
if [ ! -f "$clip" ]; then
    echo "tacoma.sh: $clip not found (see shared/data/README.md); set TACOMA_CLIP" >&2
    exit 2
fi
mkdir -p "$out" "$data"
deck=0,160,140,125,190,120,190,215,0,215   # deck surface and curb in frame 0 (full-frame pixels)
# Dense: the ROI just holds the deck polygon. KLT: a taller ROI, so its corners can follow the
# deck's ~25 px swings without leaving the crop (in the tight one every feature is lost in 0.7 s).
"$refflow" track "$clip" --polygon "$deck" --roi 0,110,200,110 --grid-step 4 --jobs 2 \
    --out "$data/deepflow.csv" --no-progress
"$refflow" track "$clip" --polygon "$deck" --roi 0,60,240,190 --method klt \
    --out "$data/klt.csv" --no-progress
"$refflow" pois "$clip" --polygon "$deck" --roi 0,60,240,190 --grid-step 4 --out "$out/tacoma_pois.png"
"$refflow" plot "$data/deepflow.csv" "$data/klt.csv" --units px \
    --title "Tacoma Narrows deck (no ground truth): deepflow vs KLT" --out "$out/tacoma_displacement.png"
# Four regions in one run: a labelled mask (grey 1..4) of the near deck in three pieces along
# the curb and the far deck edge against the sky (full-frame pixels of frame 0).
"$root/.venv/bin/python" - "$data/regions.png" <<'EOF'
import sys

import cv2
import numpy as np

labels = np.zeros((250, 334), np.uint8)
near = np.zeros_like(labels)
cv2.fillPoly(near, [np.array([[0, 160], [140, 125], [190, 120], [190, 215], [0, 215]], np.int32)], 1)
columns = np.arange(labels.shape[1])[None, :]
for label, (x0, x1) in enumerate(((0, 60), (65, 125), (130, 191)), start=1):
    labels[(near > 0) & (columns >= x0) & (columns < x1)] = label
cv2.fillPoly(labels, [np.array([[245, 86], [330, 76], [330, 96], [245, 104]], np.int32)], 4)
if not cv2.imwrite(sys.argv[1], labels):
    sys.exit(f"cannot write {sys.argv[1]}")
EOF
# With the defaults deepflow measures the near curb's pieces with the dense flow (their
# outline's background does not stand still: refused) and flags a region only where its
# typical uncertainty is above 0.35 px and 0.03 of its motion's range; the figure shows
# every reading kept (`refflow merge --max-typical-sigma 0` of the same run), as its title says.
"$refflow" track "$clip" --mask "$data/regions.png" --roi 0,60,334,165 --grid-step 4 --jobs 2 \
    --out "$data/regions.csv" --raw-tracks "$data/regions.npz" --no-progress
"$refflow" merge "$data/regions.npz" --max-typical-sigma 0 --out "$data/regions_kept.csv"
"$refflow" pois "$clip" --mask "$data/regions.png" --roi 0,60,334,165 --grid-step 4 \
    --out "$out/tacoma_regions_pois.png"
"$refflow" plot "$data/regions_kept.csv" --units px \
    --title "Tacoma deck at four places, one run, kept with --max-typical-sigma 0 (no ground truth)" \
    --out "$out/tacoma_regions.png"
