#!/usr/bin/env bash
# Issue 4's benchmarks in one command, side by side in the same run:
#   Victoria Park against GTSAM 4.3 LM and iSAM2, MRCLAM 6 per robot against GTSAM LM and GNC-TLS, and the
#   EM-SAM scaling curve (office runs, 1k to 100k poses, time and peak memory per EM round).
# The bootstrap installs gtsam (requirements/python.txt). Writes every table and figure to
# bench/results/ and concatenates the tables into bench/results/real_data.md. Exit status 1 if any benchmark misses its target.
#   bash bench/real_data.sh          # about 15 minutes on 2 cores
set -uo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh || exit 1
# shellcheck source=/dev/null
source scripts/env.sh
status=0
python bench/victoria_park_gtsam.py || status=1
python bench/mrclam_gtsam.py || status=1
python bench/em_sam_office.py --repeats 3 || status=1
cat bench/results/victoria_park_gtsam.md bench/results/mrclam_gtsam.md \
  bench/results/em_sam_office.md > bench/results/real_data.md
echo "bench/real_data.sh: tables in bench/results/real_data.md (exit $status)"
exit $status
