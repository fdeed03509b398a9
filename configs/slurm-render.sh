#!/bin/bash
# Render a scene on a Slurm allocation: the coordinator runs on the first node of the job,
# one worker per task on all nodes; workers exchange image pieces directly over QUIC.
#
#   sbatch --nodes=4 --ntasks-per-node=2 configs/slurm-render.sh configs/demo.toml out.png [RENDER ARGS...]
#
# Arguments after OUT go to `coordinator render` as they are (e.g. --exr out.exr, --size
# 1920x1080, --orbit 100, --set KEY=VALUE).
# Needs: the `coordinator` and `worker` binaries on PATH (cargo build --release) on every
# node, and the scene's stores on a file system all nodes see (workers open the same paths).
# STRATA_QUIC_MTU=N starts QUIC datagrams at N bytes on coordinator and workers alike
# (cluster.quic_mtu; default 1200): set it only where every link carries it (jumbo frames).
#SBATCH --job-name=strata-render
#SBATCH --time=00:30:00
#SBATCH --cpus-per-task=8
set -euo pipefail

SCENE=${1:?usage: slurm-render.sh SCENE.toml OUT.png}
OUT=${2:?usage: slurm-render.sh SCENE.toml OUT.png [RENDER ARGS...]}
shift 2
PORT=${STRATA_PORT:-7000}
WORKERS=${SLURM_NTASKS:?run under sbatch/salloc}
MTU=${STRATA_QUIC_MTU:-1200}

# A run folder on the shared file system, readable only by us: the secret and the
# coordinator's certificate fingerprint travel through it.
RUNS=${STRATA_RUN_DIR:-$HOME/.strata-runs}
mkdir -p -m 700 "$RUNS"
RUN=$(mktemp -d "$RUNS/run.XXXXXX")
chmod 700 "$RUN"
trap 'rm -rf "$RUN"' EXIT
head -c 32 /dev/urandom | od -An -tx1 | tr -d ' \n' > "$RUN/secret"; echo >> "$RUN/secret"

COORD_HOST=$(scontrol show hostnames "$SLURM_JOB_NODELIST" | head -n 1)

# The coordinator listens on all interfaces and waits for $WORKERS workers (cluster.spawn = false).
coordinator render "$SCENE" -o "$OUT" --workers "$WORKERS" \
    --set cluster.spawn=false \
    --set "cluster.listen=\"0.0.0.0:$PORT\"" \
    --set "cluster.secret_file=\"$RUN/secret\"" \
    --set "cluster.fingerprint_file=\"$RUN/fingerprint\"" \
    --set cluster.connect_timeout_s=300 \
    --set "cluster.quic_mtu=$MTU" "$@" &
COORD=$!

# Workers need the fingerprint, which exists once the coordinator listens.
for _ in $(seq 300); do [ -s "$RUN/fingerprint" ] && break; sleep 1; done
[ -s "$RUN/fingerprint" ] || { echo "coordinator did not start" >&2; kill $COORD; exit 1; }

srun --kill-on-bad-exit=1 worker --connect "$COORD_HOST:$PORT" \
    --fingerprint-file "$RUN/fingerprint" --secret-file "$RUN/secret" \
    --connect-timeout-s 300 --quic-mtu "$MTU" &
WORKERS_PID=$!

STATUS=0
wait $COORD || STATUS=$?
wait $WORKERS_PID || true
exit $STATUS
