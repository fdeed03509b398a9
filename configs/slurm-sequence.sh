#!/bin/bash
# Render a frame sequence as a Slurm job array: each array task renders its own range of
# frames on its node with local worker processes, and skips frames whose outputs already
# exist complete, so a re-submitted array resumes where a killed one stopped.
#
#   sbatch --array=0-9 configs/slurm-sequence.sh SCENE.toml PATH.toml 'out/frame_%05d.png' 24
#
# renders frames 0..24, 24..48, … of the camera path, 24 per task. With `--orbit N` instead
# of a path file, pass `orbit:N` as PATH.toml. Needs the `coordinator` binary on PATH on every
# node and the scene's stores on a file system all nodes see.
#SBATCH --job-name=strata-sequence
#SBATCH --time=02:00:00
#SBATCH --nodes=1
#SBATCH --cpus-per-task=16
set -euo pipefail

SCENE=${1:?usage: slurm-sequence.sh SCENE.toml PATH.toml|orbit:N OUT_%05d.png FRAMES_PER_TASK}
CAMERA=${2:?camera path file or orbit:N}
OUT=${3:?output pattern with %05d}
PER=${4:?frames per array task}
TASK=${SLURM_ARRAY_TASK_ID:?submit with sbatch --array}

FIRST=$((TASK * PER))
LAST=$((FIRST + PER))
case "$CAMERA" in
  orbit:*) SEQ=(--orbit "${CAMERA#orbit:}") ;;
  *) SEQ=(--path "$CAMERA") ;;
esac
mkdir -p "$(dirname "$OUT")"
# One worker process per 2 cores of the node (at least one). A range that runs past the
# sequence's end is cut there (with a warning); a task whose first frame is past the end
# fails, so submit no more tasks than the sequence fills.
CPUS=${SLURM_CPUS_PER_TASK:-2}
W=$(( CPUS / 2 > 0 ? CPUS / 2 : 1 ))
exec coordinator render "$SCENE" "${SEQ[@]}" --frames "$FIRST..$LAST" -o "$OUT" \
    --workers "$W" --stats "${OUT%%_%*}_task$TASK.jsonl"
