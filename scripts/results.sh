#!/usr/bin/env bash
# The runs behind docs/results.md and the README's results table, then the page itself
# and the gallery (`make results`). Each run writes under runs/ (ignored by git); the page
# cites each run's command, code, date and machine. About 70 minutes on 2 cores, an hour
# more for the pollinator sweep and 16 minutes for its search. Runs only
# from a clean tree: every number on the page is then the commit's it names.
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ -n $(git status --porcelain --untracked-files=no) ]]; then
    echo "make results: the tree has uncommitted changes; commit them first, so every run" \
        "names the code it ran" >&2
    exit 2
fi
flowerpose=.venv/bin/flowerpose
# The authors' plant 3 at runs/paper-plant-3, as `data fetch` makes it (a developer's copy
# under FLOWERPOSE_SHARED is linked there instead of downloaded), so the page's commands
# name a folder every user can make.
real=runs/paper-plant-3
shared=${FLOWERPOSE_SHARED:-../shared}/real/paper-plant-3
if [[ ! -e $real ]]; then
    mkdir -p runs
    if [[ -d $shared ]]; then
        ln -s "$(cd "$shared" && pwd)" "$real"
    else
        $flowerpose data fetch paper-plant-3 --to "$real"
    fi
fi
$flowerpose eval --suite scan-3 --out runs/scan-3 -q
$flowerpose eval --suite oracle-10 --out runs/oracle-10 -q
$flowerpose eval --suite field-10 --out runs/field-10 -q
$flowerpose eval --source real "$real" --compare upstream --out runs/real3 -q
$flowerpose stress --source real "$real" --thin 0.5,0.2,0.1,0.07,0.05,0.03 --cut 0.25,0.5 \
    --drop-views 3 --repeats 5 --compare upstream --out runs/stress-real3 -q
# The field preset at plant 3's density (its flowers hold 818 points, fidelity.json's
# median), for the simulator's predictions against the real plant's intervals.
$flowerpose eval --source oracle --preset field --plants 10 --seed 0 \
    --set 'sim.degrade.points_per_flower=[818, 818]' --out runs/field-818 -q
$flowerpose fidelity "$real" runs/field-818 --out runs/fidelity -q
$flowerpose bench --points 125000 1000000 --repeat 7 --out runs/bench -q
$flowerpose eval --task pollinate --source oracle --plants 10 --seed 0 \
    --set 'pollination.curve_angles_deg=[0, 15, 30, 45, 55, 65, 75]' --out runs/pollinate-10 -q
$flowerpose eval --task pollinate --source oracle --preset field --plants 10 --seed 0 \
    --out runs/pollinate-field-10 -q
# Which pollinator reaches the flowers: the shaft's reach and offset, without the close look.
$flowerpose sweep --task pollinate --source oracle --preset field --plants 10 --seed 0 \
    --grid pollinate.tool.reach_m=0.2,0.24,0.28 --grid pollinate.tool.offset_down_m=0.07,0.1 \
    --set pollinate.look.views=0 --out runs/sweep-tool -q
# The same question as a search, chosen on plants the search never trained on.
$flowerpose tune --task pollinate --space examples/tuning/tool.toml --trials 6 \
    --preset field --plants 3 --seed 0 --sampler-seed 1 --workers 2 \
    --set pollinate.look.views=0 --out runs/tune-tool --overwrite -q
# Real photographs to a cloud three ways, timed and checked against the calibrated cameras
# (the shared copy where there is one, else the published set, fetched).
photos=${FLOWERPOSE_SHARED:-../shared}/real-photos/romi-arabidopsis
if [[ ! -d $photos ]]; then
    photos=runs/romi-arabidopsis
    [[ -d $photos ]] || $flowerpose data fetch romi-arabidopsis --to "$photos" > /dev/null
fi
$flowerpose bench --photos "$photos" --out runs/photos --overwrite -q
$flowerpose results runs/scan-3/report.json runs/oracle-10/report.json runs/field-10/report.json \
    runs/real3/report.json runs/pollinate-10/report.json runs/pollinate-field-10/report.json \
    runs/stress-real3/stress.json runs/fidelity/fidelity.json runs/bench/bench.json \
    runs/photos/photo_bench.json \
    --figure docs/accuracy.png > docs/results.md.partial
mv docs/results.md.partial docs/results.md
# The docs' result blocks (the README's table among them) from these runs.
.venv/bin/python scripts/result_blocks.py runs
bash scripts/gallery.sh
echo "docs/results.md, and the result blocks of README.md, DESIGN.md and the guides"
