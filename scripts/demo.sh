#!/usr/bin/env bash
# Set everything up (scripts/bootstrap.sh), then run the main job on the bundled sample bag
# and print what it found. Results go to out/demo/.
#
# Today the main job is the bring-up pipeline: the sample bag is replayed through the graph
# runner (graphs/bag_replay.yaml) and recorded back, and both bags are summarized.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/bootstrap.sh"
# shellcheck source=scripts/env.sh
source "$ROOT/scripts/env.sh"
cd "$ROOT"

SAMPLE="$ROOT/bags/ubiquity_aruco"
OUT="$ROOT/out/demo"
rm -rf "$OUT"
mkdir -p "$OUT"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$((100 + $$ % 100))}"

echo "== sample bag"
bag_info "$SAMPLE"
echo
echo "== replaying it through slam_run (graph: bag_replay.yaml) and recording the topics"
slam_run "$ROOT/src/slam_bringup/graphs/bag_replay.yaml" \
  --bag "$SAMPLE" --record "$OUT/replayed" --exit-when-player-done
echo
echo "== what the recorder captured"
bag_info "$OUT/replayed"
