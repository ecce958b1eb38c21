#!/usr/bin/env bash
# The monocular pipeline of paper 001 on the bundled rendered bag (run by
# `bash scripts/demo.sh --monoslam`): set everything up, replay bags/dynamic_camera.mcap (a
# hand-held camera in a room with moving textured objects, 10 s, ground truth included)
# through marker_detector + feature_tracker -> monoslam <-> shadow_filter (real rclpy, graph
# monoslam_shadow.yaml), score the live trajectory against the bag's ground truth, then run
# the same front end offline over the bag (monoslam_image_evaluate): paper 001's Fig. 5
# variants (a) static features only, (b) all features, (c) with the Shadow filter, next to
# the measurement-level (c). Results and figures go to out/demo_monoslam/.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/bootstrap.sh"
# shellcheck source=scripts/env.sh
source "$ROOT/scripts/env.sh"
cd "$ROOT"

SAMPLE="$ROOT/bags/dynamic_camera.mcap"
OUT="$ROOT/out/demo_monoslam"
rm -rf "$OUT" "$ROOT/out/monoslam_shadow"
mkdir -p "$OUT"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$((100 + $$ % 100))}"

echo "== sample bag"
bag_info "$SAMPLE"
echo
echo "== marker_detector, feature_tracker, monoslam and shadow_filter on the bag (slam_run monoslam_shadow.yaml, paced replay)"
slam_run monoslam_shadow.yaml --bag "$SAMPLE" --paced --exit-when-player-done 2>&1 | tee "$OUT/live.log"
mv "$ROOT/out/monoslam_shadow" "$OUT/live"
mv "$OUT/live.log" "$OUT/live/run.log"
echo
echo "== what the live nodes did (their final counts; full log: $OUT/live/run.log)"
grep -E '\[(monoslam|shadow_filter)\]: done:' "$OUT/live/run.log" | sed -E 's/^.*\[(monoslam|shadow_filter)\]: done: /\1: /' \
  || echo "the nodes printed no final counts: see $OUT/live/run.log" >&2
echo
python - "$SAMPLE" "$OUT/live/trajectory.tum" <<'PYEOF'
import sys
from pathlib import Path
import numpy as np
from slam_evaluation.monoslam_image_sources import bag_source
truth = {frame.stamp_ns: frame.centre_m for frame in bag_source(Path(sys.argv[1])).frames()}
rows = np.loadtxt(sys.argv[2], ndmin=2)
errors = [np.linalg.norm(row[1:4] - truth[int(round(row[0] * 1e9))]) for row in rows
          if int(round(row[0] * 1e9)) in truth]
print(f'live monoslam: {len(rows)} poses for {len(truth)} images; camera position error '
      f'against the ground truth: median {np.median(errors):.3f} m, RMS '
      f'{np.sqrt(np.mean(np.square(errors))):.3f} m, max {np.max(errors):.3f} m')
PYEOF
echo
echo "== the same front end offline, Fig. 5 variants (monoslam_image_evaluate)"
monoslam_image_evaluate --bag "$SAMPLE" --out "$OUT/evaluation"
echo "figures: $OUT/evaluation/*.png; trajectory: $OUT/live/trajectory.tum"
