#!/usr/bin/env bash
# A single-node Slurm on this machine (Debian's slurm-wlm and munge; Slurm 22.05), for the tests
# and for trying the Slurm path before a real cluster: slurmctld and slurmd on 127.0.0.1, one
# partition `handedit` with this machine's cores.
#   bash deploy/slurm-local.sh start [DIR]   config, state and logs in DIR (default runs/slurm); prints
#                                            `export SLURM_CONF=...`: eval it, then sbatch/srun/squeue work
#   bash deploy/slurm-local.sh stop [DIR]
#   bash deploy/slurm-local.sh env [DIR]     print the export line again
# Needs root (the daemons run as root here; munged as the munge user). Ports: SLURM_PORT (default
# 6817) for slurmctld, +1 for slurmd.
set -euo pipefail
cmd=${1:-start}
DIR=$(realpath -m "${2:-runs/slurm}")
PORT=${SLURM_PORT:-6817}
NODE=handedit-node
conf="$DIR/slurm.conf"

install_packages() {
  local need=()
  for pkg in slurm-wlm munge; do dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg"); done
  if [ ${#need[@]} -gt 0 ]; then
    echo "installing Debian packages: ${need[*]}" >&2
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
  fi
}

start_munge() {
  if munge -n </dev/null 2>/dev/null | unmunge >/dev/null 2>&1; then return; fi
  [ -s /etc/munge/munge.key ] || { mungekey --create --keyfile /etc/munge/munge.key >/dev/null; chown munge:munge /etc/munge/munge.key; chmod 400 /etc/munge/munge.key; }
  mkdir -p /run/munge /var/log/munge /var/lib/munge && chown munge:munge /run/munge /var/log/munge /var/lib/munge
  runuser -u munge -- /usr/sbin/munged
  for _ in $(seq 50); do munge -n </dev/null 2>/dev/null | unmunge >/dev/null 2>&1 && return; sleep 0.1; done
  echo "munged did not start (see /var/log/munge/munged.log)" >&2; exit 1
}

write_conf() {
  mkdir -p "$DIR/state" "$DIR/spool" "$DIR/jobs"
  local cpus mem
  cpus=$(nproc)
  mem=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 - 1024 ))
  cat > "$conf" <<CONF
ClusterName=handedit
SlurmctldHost=$(hostname -s)(127.0.0.1)
MailProg=/bin/true
SlurmctldPort=$PORT
SlurmdPort=$((PORT + 1))
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
MpiDefault=none
ReturnToService=2
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/slurmctld.log
SlurmdLogFile=$DIR/slurmd.log
JobCompType=jobcomp/none
AccountingStorageType=accounting_storage/none
SlurmctldTimeout=30
SlurmdTimeout=30
InactiveLimit=0
KillWait=5
NodeName=$NODE NodeAddr=127.0.0.1 NodeHostname=$(hostname) CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=handedit Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
CONF
}

running() { [ -f "$DIR/$1.pid" ] && kill -0 "$(cat "$DIR/$1.pid")" 2>/dev/null; }

case "$cmd" in
  start)
    [ "$(id -u)" -eq 0 ] || { echo "deploy/slurm-local.sh runs the Slurm daemons as root: run it as root (CI does)" >&2; exit 1; }
    install_packages
    start_munge
    write_conf
    running slurmctld || /usr/sbin/slurmctld -f "$conf" -i
    running slurmd || /usr/sbin/slurmd -f "$conf" -N "$NODE"
    export SLURM_CONF="$conf"
    for _ in $(seq 100); do
      state=$(timeout 3 sinfo -h -N -o %t 2>/dev/null | head -1 || true)
      case "$state" in idle*|mix*|alloc*) echo "export SLURM_CONF=$conf"; exit 0;; esac
      sleep 0.2
    done
    echo "Slurm did not come up (node state '${state:-none}'); see $DIR/slurmctld.log and $DIR/slurmd.log" >&2
    exit 1
    ;;
  stop)
    for d in slurmd slurmctld; do running "$d" && kill "$(cat "$DIR/$d.pid")" || true; done
    for _ in $(seq 50); do running slurmd || running slurmctld || exit 0; sleep 0.1; done
    ;;
  env)
    echo "export SLURM_CONF=$conf"
    ;;
  *)
    echo "usage: bash deploy/slurm-local.sh start|stop|env [DIR]" >&2; exit 2;;
esac
