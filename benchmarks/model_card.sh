#!/usr/bin/env bash
# The model card's held-out evaluation (docs/models.md, "How good it is") for one model file.
# usage: bash benchmarks/model_card.sh MODEL DATA_DIR [THREADS] [PER_PAIR_CSV]
#   MODEL     a .safetensors file or a shipped name ("small")
#   DATA_DIR  the folder holding the held-out sets eval_s424242, eval_p4_s434343, bench_s525252 and, when
#             present, eval_cam_s464646 (rendered from their seeds: docs/models.md, "Reproduce")
# The real-photograph rows need Debian's opencv-doc package (apt-get install opencv-doc).
#   PER_PAIR_CSV  also save every pair's rotation / direction error there (replaced), so that two models can be
#                 compared pair by pair: python benchmarks/paired.py A.csv B.csv
# Side by side with another model: save each output and run python benchmarks/compare_cards.py A.txt B.txt.
set -euo pipefail
if [ $# -lt 2 ]; then
  echo "usage: bash benchmarks/model_card.sh MODEL DATA_DIR [THREADS] [PER_PAIR_CSV]" >&2
  exit 2
fi
M=$1 D=$2 T=${3:-2} PP=()
if [ $# -ge 4 ]; then
  PP=(--per-pair "$(realpath -m "$4")")
  rm -f "${PP[1]}"
fi
[ -e "$M" ] && M=$(realpath "$M")   # a file path; otherwise a shipped name such as "small"
D=$(realpath -m "$D")
cd "$(dirname "$0")/.."             # the repository root: training.evaluate runs as a module from there
for s in eval_s424242 eval_p4_s434343 bench_s525252; do
  [ -d "$D/$s" ] || { echo "model_card.sh: expected the held-out set $D/$s (docs/models.md, Reproduce)" >&2; exit 2; }
done
PY=${PYTHON:-python}
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl} OMP_NUM_THREADS=$T
echo "== eval_s424242"; $PY -m training.evaluate --model "$M" --data "$D/eval_s424242" --threads "$T" "${PP[@]}"
echo "== eval_p4_s434343"; $PY -m training.evaluate --model "$M" --data "$D/eval_p4_s434343" --threads "$T" "${PP[@]}"
if [ -d "$D/eval_cam_s464646" ]; then  # pairs taken with one camera (session 18 on; docs/data.md)
  echo "== eval_cam_s464646"; $PY -m training.evaluate --model "$M" --data "$D/eval_cam_s464646" --threads "$T" "${PP[@]}"
else
  echo "== eval_cam_s464646: skipped ($D/eval_cam_s464646 missing: docs/models.md, Reproduce)"
fi
echo "== bench_s525252"; $PY benchmarks/bench_pose.py --data "$D/bench_s525252" --pairs 200 --model "$M" --threads 1 "${PP[@]}"
REAL=/usr/share/doc/opencv-doc/examples/data
if [ -d "$REAL" ]; then
  echo "== real"; $PY benchmarks/bench_real.py --data "$REAL" --model "$M" "${PP[@]}"
else
  echo "== real: skipped ($REAL missing: apt-get install opencv-doc)"
fi
