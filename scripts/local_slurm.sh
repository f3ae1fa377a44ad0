#!/usr/bin/env bash
# A single-node SLURM cluster on this machine, for tests and for trying the cluster path by hand.
#   bash scripts/local_slurm.sh install   # Debian's slurm-wlm and munge (as root)
#   bash scripts/local_slurm.sh start     # writes /etc/slurm/slurm.conf, starts munged, slurmctld, slurmd
#   bash scripts/local_slurm.sh stop
# Partitions `cpu` and `gpu` both map to this node (it has no GPU: the test profile asks for none).
# No accounting daemon: `sacct` answers nothing, so Snakemake needs `--slurm-status-command squeue`
# (profiles/slurm-local sets it). srun inside jobs reads only /etc/slurm/slurm.conf, hence that path.
set -euo pipefail
STATE=${VQB_SLURM_STATE:-/var/spool/vqb-slurm}

install() {
    command -v slurmctld >/dev/null && command -v munged >/dev/null && return 0
    # Without recommends: slurm-wlm-plugins would add ~30 packages (HDF5, ROCm, IPMI, InfluxDB, MySQL
    # plugins) this cluster never loads. The package lists are refreshed only when the install fails
    # without that (.ci/run has usually refreshed them moments before, to install chromium).
    local packages=(slurm-wlm munge)
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${packages[@]}" >/dev/null 2>&1 || {
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${packages[@]}" >/dev/null
    }
}

start() {
    local node cpus mem
    node=$(hostname -s)
    cpus=$(nproc)
    mem=$(( $(awk '/MemTotal/{print $2}' /proc/meminfo) / 1024 - 1024 ))
    mkdir -p "$STATE/ctld" "$STATE/d" /etc/slurm /run/munge /var/log/munge /var/lib/munge
    cat > /etc/slurm/slurm.conf <<CONF
ClusterName=vqb-local
SlurmctldHost=$node
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/d
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$STATE/slurmctld.log
SlurmdLogFile=$STATE/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
MpiDefault=none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ReturnToService=2
JobRequeue=1
# A requeued job may start again only cred_expire + 1 s after its requeue (120 s by default, 5 the least
# slurm accepts), then at the next scheduling pass that finds it eligible (backfill's, every bf_interval s;
# 30 by default). A job's credentials are checked within a second of their creation on this one node.
AuthInfo=cred_expire=10
SchedulerParameters=bf_interval=5
KillWait=5
MinJobAge=300
NodeName=$node CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=cpu Nodes=$node Default=YES MaxTime=INFINITE State=UP OverSubscribe=NO
PartitionName=gpu Nodes=$node MaxTime=INFINITE State=UP
CONF
    if [ ! -s /etc/munge/munge.key ]; then
        dd if=/dev/urandom bs=1 count=1024 of=/etc/munge/munge.key 2>/dev/null
    fi
    chown munge:munge /etc/munge/munge.key /run/munge /var/log/munge /var/lib/munge
    chmod 400 /etc/munge/munge.key
    pgrep -x munged >/dev/null || runuser -u munge -- /usr/sbin/munged
    pgrep -x slurmctld >/dev/null || slurmctld -c
    pgrep -x slurmd >/dev/null || slurmd
    for _ in $(seq 60); do
        # A run killed mid-job (its tasks outlived KillWait) leaves the node drained: back into service.
        if sinfo -h -o '%T' 2>/dev/null | grep -q '^drain'; then
            scontrol update NodeName="$node" State=RESUME || true
        fi
        if sinfo -h -o '%T' 2>/dev/null | grep -qE '^(idle|mixed|allocated)'; then
            echo "local_slurm: cluster up on $node ($cpus CPUs, $mem MB)"
            return 0
        fi
        sleep 1
    done
    echo "local_slurm: node did not become idle; see $STATE/slurmctld.log and $STATE/slurmd.log" >&2
    sinfo >&2 || true
    return 1
}

stop() {
    scancel --full --quiet --user=root 2>/dev/null || true
    pkill -x slurmd 2>/dev/null || true
    pkill -x slurmctld 2>/dev/null || true
    # (two pgreps: pgrep matches nothing when its pattern is longer than a process name's 15 characters)
    for _ in $(seq 20); do pgrep -x slurmd >/dev/null || pgrep -x slurmctld >/dev/null || break; sleep 0.5; done
    # Clients of the stopped cluster give up at once: scontrol would retry the controller once a second
    # for MessageTimeout (10 s), and Snakemake's SLURM executor plugin runs `scontrol show config` at
    # every Snakemake start, local runs included (`snakemake -n`: 11 s instead of 2 s). `start` rewrites
    # the file; a slurm.conf that is not this script's is left alone.
    if grep -qx 'ClusterName=vqb-local' /etc/slurm/slurm.conf 2>/dev/null; then
        sed -i '/^MessageTimeout=/d' /etc/slurm/slurm.conf
        echo "MessageTimeout=1" >> /etc/slurm/slurm.conf
    fi
    echo "local_slurm: stopped"
}

"${1:?usage: local_slurm.sh install|start|stop}"
