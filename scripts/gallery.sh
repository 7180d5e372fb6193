#!/usr/bin/env bash
# The pictures of docs/gallery.md and the sample outputs of docs/what-you-get.md, made
# from real runs (`make gallery`; `make results` runs it too). Each run writes under
# runs/gallery/ (ignored by git); the pictures go to docs/images/gallery/, the samples to
# docs/samples/. About 8 minutes on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
flowerpose=.venv/bin/flowerpose
runs=runs/gallery
images=docs/images/gallery
samples=docs/samples
mkdir -p "$runs" "$images" "$samples"

$flowerpose plant --seed 3 --out "$runs/plant3" --overwrite -q
$flowerpose detect "$runs/plant3/cloud.ply" --out "$runs/detect3" --overwrite -q
$flowerpose score "$runs/detect3/flowers.json" "$runs/plant3/plant.json" --out "$runs/score3" \
    --overwrite -q > /dev/null
$flowerpose eval --source oracle --plants 2 --seed 3 --task pollinate --out "$runs/eval2" \
    --overwrite -q > /dev/null
$flowerpose stress --source oracle --plants 2 --seed 3 --thin 0.5,0.2,0.1,0.05 --noise 0.001,0.002 \
    --exposure 1 --cast 0 --cut 0 --drop-views 0 \
    --out "$runs/stress2" --overwrite -q > /dev/null
# A short simulated scan: a frame every 20 s of the bot's clock, small frames, and MuJoCo's
# view of the gantry filming (preview.mp4).
$flowerpose scan --sim --plant "$runs/plant3" --frame-rate 0.05 --width 640 --height 360 \
    --out "$runs/scan3" -q > /dev/null

# Real photographs from the images alone (the guide "Your own photographs"): the shared
# copy where there is one, else the published set, fetched.
photos=${FLOWERPOSE_SHARED:-../shared}/real-photos/romi-arabidopsis
if [[ ! -d $photos ]]; then
    photos=runs/romi-arabidopsis
    [[ -d $photos ]] || $flowerpose data fetch romi-arabidopsis --to "$photos" > /dev/null
fi
$flowerpose frames --images "$photos/images" --out "$runs/photos/frames" --overwrite -q > /dev/null
$flowerpose reconstruct "$runs/photos/frames" --out "$runs/photos/recon" --overwrite -q > /dev/null

.venv/bin/python scripts/gallery.py "$runs" "$images" "$samples"
echo "$images, $samples"
