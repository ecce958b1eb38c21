#!/usr/bin/env bash
# The image pipeline on the bundled camera bag (run by `bash scripts/demo.sh --camera`):
# set everything up, replay bags/office_camera.mcap through marker_detector ->
# odometry_ingest -> em_sam_mapper (real rclpy, graph em_sam_office_camera.yaml), then run the
# detector offline over the same bag (marker_detect_bag) and score EM-SAM against ground
# truth (em_sam_evaluate). Results and figures go to out/demo_camera/.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/bootstrap.sh"
# shellcheck source=scripts/env.sh
source "$ROOT/scripts/env.sh"
cd "$ROOT"

SAMPLE="$ROOT/bags/office_camera.mcap"
OUT="$ROOT/out/demo_camera"
rm -rf "$OUT" "$ROOT/out/em_sam_camera"
mkdir -p "$OUT"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$((100 + $$ % 100))}"

echo "== sample bag"
bag_info "$SAMPLE"
echo
echo "== marker_detector + EM-SAM nodes on the bag (slam_run em_sam_office_camera.yaml, paced replay)"
slam_run em_sam_office_camera.yaml --bag "$SAMPLE" --paced --exit-when-player-done
mv "$ROOT/out/em_sam_camera" "$OUT/live_mapper"
echo
echo "== the same detector offline (marker_detect_bag)"
marker_detect_bag "$SAMPLE" --output "$OUT/detected" \
  --params "$ROOT/src/marker_detector/config/marker_detector.yaml" \
  --params "$ROOT/src/marker_detector/config/office_camera.yaml"
echo
echo "== evaluation against ground truth (em_sam_evaluate)"
em_sam_evaluate "$OUT/detected" --output "$OUT/evaluation" \
  --live-report "$OUT/live_mapper/em_sam_report.json"
echo
python - "$OUT/live_mapper/em_sam_report.json" <<'PYEOF'
import json, sys
report = json.load(open(sys.argv[1]))
print(f"live em_sam_mapper from images ({report['mode']}): {report['num_keyframes']} keyframes, "
      f"{report['num_landmarks']} landmarks, moveable ids {report['moveable_ids']}, "
      f"{report['em_iterations']} EM iterations, {report['timings_s']['total']:.2f} s")
PYEOF
echo "figures: $OUT/live_mapper/*.png and $OUT/evaluation/*/*.png"
