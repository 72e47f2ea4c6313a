#!/usr/bin/env bash
# A one-node SLURM on this machine (slurmctld + slurmd + munge, all on
# localhost), to run `tiledsm ... --cluster slurm.yaml` end to end on a real
# batch system (benchmarks/slurm_run.py).
#
#   sudo apt-get install -y slurmctld slurmd slurm-client munge   # Debian/Ubuntu
#   sudo benchmarks/slurm_local.sh start     # configure and start; waits until the node is idle
#   sinfo; squeue                            # a partition "debug" of one node: this machine
#   sudo benchmarks/slurm_local.sh stop
#
# Runs as root (the daemons and the jobs run as root too: a test bed, not a
# production set-up). It writes /etc/slurm/slurm.conf and a munge key only if
# they are absent or were written by this script (they carry its marker).
# No cgroups: processes are tracked by /proc (proctrack/linuxproc), so it also
# runs in a container. Logs: /var/log/slurm-local/.
set -euo pipefail

ACTION=${1:-start}
STATE=${SLURM_LOCAL_STATE:-/var/lib/slurm-local}
LOGS=/var/log/slurm-local
CONF=/etc/slurm/slurm.conf
MARK="# written by tiledsm benchmarks/slurm_local.sh"

stop() {
    for pidfile in /run/slurmd-local.pid /run/slurmctld-local.pid /run/munge/munged.pid; do
        if [[ -f $pidfile ]]; then
            kill "$(cat "$pidfile")" 2>/dev/null || true
            rm -f "$pidfile"
        fi
    done
}

if [[ $ACTION == stop ]]; then
    stop
    exit 0
fi
[[ $ACTION == start ]] || { echo "usage: $0 start|stop" >&2; exit 2; }
[[ $(id -u) == 0 ]] || { echo "$0: run as root (it starts the SLURM daemons)" >&2; exit 2; }
for exe in slurmctld slurmd munged sinfo; do
    command -v "$exe" >/dev/null || { echo "$0: $exe missing: apt-get install -y slurmctld slurmd slurm-client munge" >&2; exit 2; }
done
if [[ -f $CONF ]] && ! grep -qF "$MARK" "$CONF"; then
    echo "$0: $CONF exists and was not written by this script: not touching it" >&2
    exit 2
fi

host=$(hostname -s)
cpus=$(nproc)
mem_mb=$(awk '/MemTotal/ {print int($2 / 1024 * 0.9)}' /proc/meminfo)
mkdir -p /etc/slurm "$STATE/ctld" "$STATE/d" "$LOGS" /run/munge /var/lib/munge /var/log/munge /etc/munge

# munge: the key every daemon and client shares
if [[ ! -s /etc/munge/munge.key ]]; then
    dd if=/dev/urandom bs=1 count=1024 of=/etc/munge/munge.key status=none
fi
chown -R munge:munge /etc/munge /run/munge /var/lib/munge /var/log/munge 2>/dev/null || true
chmod 700 /etc/munge && chmod 400 /etc/munge/munge.key
if ! munge -n >/dev/null 2>&1; then
    if id munge >/dev/null 2>&1; then
        runuser -u munge -- munged --pid-file=/run/munge/munged.pid
    else
        munged --force --pid-file=/run/munge/munged.pid
    fi
fi

cat > "$CONF" <<CONF
$MARK
ClusterName=tiledsm-local
SlurmctldHost=$host
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/d
SlurmctldPidFile=/run/slurmctld-local.pid
SlurmdPidFile=/run/slurmd-local.pid
SlurmctldLogFile=$LOGS/slurmctld.log
SlurmdLogFile=$LOGS/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SchedulerType=sched/backfill
ReturnToService=2
MpiDefault=none
NodeName=$host CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONF

stop_daemons_only() {
    for pidfile in /run/slurmd-local.pid /run/slurmctld-local.pid; do
        [[ -f $pidfile ]] && { kill "$(cat "$pidfile")" 2>/dev/null || true; rm -f "$pidfile"; }
    done
    sleep 1
}
stop_daemons_only
slurmctld -c    # -c: a clean start (no jobs of an earlier start)
slurmd
for _ in $(seq 60); do
    state=$(sinfo -h -n "$host" -o %t 2>/dev/null || true)
    if [[ $state == idle ]]; then
        echo "SLURM on $host: partition debug, $cpus CPUs, $mem_mb MB (sinfo: $state)"
        exit 0
    fi
    sleep 1
done
echo "$0: the node did not become idle in 60 s (sinfo: ${state:-nothing}); see $LOGS" >&2
exit 1
