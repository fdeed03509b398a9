#!/usr/bin/env bash
# A one-node Slurm on this host, for testing configs/slurm-render.sh with the real sbatch
# and srun: munged, slurmctld and slurmd run as the calling user (root) out of DIR, on
# ports of their own, and stop with `stop`.
#
#   tests/slurm/localhost.sh start DIR [CPUS]   # then: export SLURM_CONF=DIR/slurm.conf
#   tests/slurm/localhost.sh stop DIR
#
# Needs Debian's slurm-wlm and munge (apt-get install slurm-wlm munge). Used by
# coordinator/tests/slurm.rs, which .ci/run's packages make run in CI.
set -euo pipefail
CMD=${1:?usage: localhost.sh start|stop DIR [CPUS]}
DIR=$(realpath -m "${2:?usage: localhost.sh start|stop DIR [CPUS]}")
CPUS=${3:-4}

stop() {
  for p in slurmd slurmctld; do
    [ -s "$DIR/$p.pid" ] && kill "$(cat "$DIR/$p.pid")" 2>/dev/null || true
  done
  [ -S "$DIR/munge/munge.socket" ] && munged -s --socket="$DIR/munge/munge.socket" >/dev/null 2>&1 || true
}

case "$CMD" in
  stop) stop; exit 0 ;;
  start) ;;
  *) echo "usage: localhost.sh start|stop DIR [CPUS]" >&2; exit 2 ;;
esac

for tool in munged slurmctld slurmd sbatch sinfo; do
  command -v "$tool" >/dev/null || { echo "error: $tool not found (apt-get install slurm-wlm munge)" >&2; exit 1; }
done
mkdir -p "$DIR/munge" "$DIR/state" "$DIR/spool" "$DIR/log"
chmod 711 "$DIR/munge"
head -c 1024 /dev/urandom > "$DIR/munge/munge.key"
chmod 400 "$DIR/munge/munge.key"
munged -f --key-file="$DIR/munge/munge.key" --socket="$DIR/munge/munge.socket" \
  --log-file="$DIR/munge/munged.log" --pid-file="$DIR/munge/munged.pid" --seed-file="$DIR/munge/seed"

HOST=$(hostname -s)
# Ports of this run's own, from its folder name, so runs side by side do not clash.
PORT=$(( 20000 + $(echo "$DIR" | cksum | cut -d' ' -f1) % 20000 * 2 ))
cat > "$DIR/slurm.conf" <<CONF
ClusterName=strata
SlurmctldHost=$HOST(127.0.0.1)
SlurmUser=$(id -un)
SlurmdUser=$(id -un)
AuthType=auth/munge
AuthInfo=socket=$DIR/munge/munge.socket
CredType=cred/munge
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/log/slurmctld.log
SlurmdLogFile=$DIR/log/slurmd.log
SlurmctldPort=$PORT
SlurmdPort=$((PORT + 1))
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
ReturnToService=2
SlurmdParameters=config_overrides
MpiDefault=none
JobCompType=jobcomp/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SwitchType=switch/none
NodeName=$HOST NodeAddr=127.0.0.1 CPUs=$CPUS RealMemory=1000 State=UNKNOWN
PartitionName=debug Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
CONF
export SLURM_CONF="$DIR/slurm.conf"
slurmctld -f "$SLURM_CONF" >"$DIR/log/slurmctld.out" 2>&1
slurmd -f "$SLURM_CONF" >"$DIR/log/slurmd.out" 2>&1
for _ in $(seq 100); do
  if sinfo -h -o %t 2>/dev/null | grep -qx idle; then
    echo "export SLURM_CONF=$SLURM_CONF"
    exit 0
  fi
  sleep 0.2
done
echo "error: the node did not come up idle within 20 s; sinfo says: $(sinfo 2>&1 | tail -1)" >&2
tail -5 "$DIR/log/slurmctld.log" "$DIR/log/slurmd.log" >&2 || true
stop
exit 1
