#!/usr/bin/env bash
# Set everything up, then run the main job on a bundled example: the aperture-effect factor k_A
# of the illustrative portable instrument (scenes/portable.toml) for the CIE R3 road surface,
# over the full 580-cell r-table grid, with the Mitsuba backend.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
roadgonio ka --instrument scenes/portable.toml --sample R3 --out out/portable-R3 "$@"
echo "Open out/portable-R3/ka.png for the k_A map; ka.nc / ka.csv / ka_se.csv hold the numbers, ka.json the provenance."
