#!/usr/bin/env bash
# Set everything up (scripts/bootstrap.sh), then run the main job on the bundled sample bag
# and print what it found. Results and figures go to out/demo/.
#
# The main job is EM-SAM on bags/office_moveable.mcap, a simulated run of the paper's office
# experiment (seed 7): 29 static wall markers, and 10 desk markers (ids 100-109) that move
# from office 1 to office 2 while the robot is in the corridor. The bag is replayed at 20x
# through odometry_ingest and em_sam_mapper (real rclpy, graph em_sam_office.yaml); the
# mapper writes its report (JSON + PNG) on shutdown. Then em_sam_evaluate replays the same
# bag through the same processors offline and scores five methods against ground truth,
# plus the live mapper's own result.
#
# With --camera the main job starts from pixels instead: bags/office_camera.mcap (the same
# office run seen by a simulated camera, AprilTag 36h11 markers) is replayed through
# marker_detector -> odometry_ingest -> em_sam_mapper (graph em_sam_office_camera.yaml), then
# marker_detect_bag runs the same detector offline and em_sam_evaluate scores the result.
#
# With --monoslam it runs paper 001's monocular pipeline instead (scripts/demo_monoslam.sh):
# bags/dynamic_camera.mcap through marker_detector, feature_tracker, monoslam and
# shadow_filter, then the Fig. 5 evaluation of the same bag offline.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
case "${1:-}" in
  "") ;;
  --camera) exec bash "$ROOT/scripts/demo_camera.sh" ;;
  --monoslam) exec bash "$ROOT/scripts/demo_monoslam.sh" ;;
  *) echo "usage: bash scripts/demo.sh [--camera | --monoslam]" >&2; exit 2 ;;
esac
bash "$ROOT/scripts/bootstrap.sh"
# shellcheck source=scripts/env.sh
source "$ROOT/scripts/env.sh"
cd "$ROOT"

SAMPLE="$ROOT/bags/office_moveable.mcap"
OUT="$ROOT/out/demo"
rm -rf "$OUT" "$ROOT/out/em_sam"
mkdir -p "$OUT"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$((100 + $$ % 100))}"

echo "== sample bag"
bag_info "$SAMPLE"
echo
echo "== EM-SAM nodes on the bag (slam_run em_sam_office.yaml, paced replay: the same result on any load)"
slam_run em_sam_office.yaml --bag "$SAMPLE" --paced --exit-when-player-done
mv "$ROOT/out/em_sam" "$OUT/live_mapper"
echo
echo "== evaluation against ground truth (em_sam_evaluate)"
em_sam_evaluate "$SAMPLE" --output "$OUT/evaluation" \
  --live-report "$OUT/live_mapper/em_sam_report.json"
echo
python - "$OUT/live_mapper/em_sam_report.json" <<'PYEOF'
import json, sys
report = json.load(open(sys.argv[1]))
print(f"live em_sam_mapper ({report['mode']}): {report['num_keyframes']} keyframes, "
      f"{report['num_landmarks']} landmarks, moveable ids {report['moveable_ids']}, "
      f"{report['em_iterations']} EM iterations, {report['timings_s']['total']:.2f} s")
PYEOF
echo "figures: $OUT/live_mapper/*.png and $OUT/evaluation/office_moveable/*.png"
