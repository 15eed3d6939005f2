#!/usr/bin/env bash
# A one-node SLURM on this machine (controller and compute node on 127.0.0.1), to exercise
# workflow/profiles/slurm without a cluster. Debian/Ubuntu only (apt-get); needs root.
#   bash scripts/slurm-local.sh start           # install slurm-wlm + munge if missing, write the config,
#                                               # start munged, slurmctld, slurmd; wait for an idle node
#   bash scripts/slurm-local.sh status          # sinfo / squeue
#   bash scripts/slurm-local.sh stop            # stop the three daemons (by their pid files)
#   bash scripts/slurm-local.sh smoke [DIR] [snakemake args...]
#                                               # copy the workflow to DIR (default: a new /tmp dir) and
#                                               # run the smoke config's `renders evaluate` targets there
#                                               # through --profile workflow/profiles/slurm
# Design:
# - No slurmdbd: AccountingStorageType=accounting_storage/none, so `sacct` cannot answer. The
#   executor plugin is therefore told to poll with `squeue` (--slurm-status-command squeue), and
#   MinJobAge=600 keeps finished jobs visible to squeue for 10 minutes (the plugin falls back to
#   sacct when MinJobAge is under 3x its first polling interval).
# - Finished jobs are also appended to JOBCOMP_LOG (jobcomp/filetxt), a record independent of
#   Snakemake that tests/test_slurm.py reads.
# - select/cons_tres with CR_Core_Memory: the node offers the CPUs and memory `slurmd -C` reports, so
#   SLURM never runs more CPU-requesting jobs at once than there are cores.
# - One partition, SLURM_LOCAL_PARTITION (default "local"). Accounts are not checked without
#   slurmdbd; SLURM_LOCAL_ACCOUNT (default "local") is only passed through to sbatch -A.
# - /etc/slurm/slurm.conf is written only when absent or written by this script before (a marker line);
#   a site's own configuration is never overwritten.
# - Daemons run without systemd (containers have none) and use proctrack/linuxproc, task/none: no
#   cgroups, so memory requests are scheduled but not enforced.

set -euo pipefail

SLURM_CONF_FILE="${SLURM_CONF:-/etc/slurm/slurm.conf}"
PARTITION="${SLURM_LOCAL_PARTITION:-local}"
ACCOUNT="${SLURM_LOCAL_ACCOUNT:-local}"
MARKER="# written by mcdenoise-harness scripts/slurm-local.sh"
LOG_DIR=/var/log/slurm
JOBCOMP_LOG="$LOG_DIR/jobcomp.log"
CTLD_PID=/run/slurmctld.pid
SLURMD_PID=/run/slurmd.pid
MUNGE_PID=/run/munge/munged.pid
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

log() { echo "[slurm-local] $*" >&2; }
die() { log "ERROR: $*"; exit 1; }

# True when the pid file names a live process.
running() { [[ -s "$1" ]] && kill -0 "$(cat "$1")" 2>/dev/null; }

install_packages() {
    if command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v sinfo >/dev/null \
        && command -v munged >/dev/null; then
        return 0
    fi
    command -v apt-get >/dev/null || die "slurm-wlm/munge are not installed and apt-get is unavailable"
    [[ "$(id -u)" == 0 ]] || die "installing slurm-wlm and munge needs root"
    log "apt-get install slurm-wlm munge"
    apt-get update -qq || die "apt-get update failed"
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends slurm-wlm munge >/dev/null \
        || die "apt-get install slurm-wlm munge failed"
}

write_config() {
    local node_line hostname_short mem
    if [[ -e "$SLURM_CONF_FILE" ]] && ! grep -qF "$MARKER" "$SLURM_CONF_FILE"; then
        die "$SLURM_CONF_FILE exists and was not written by this script; not overwriting it"
    fi
    hostname_short="$(hostname -s)"
    # e.g. "NodeName=vm CPUs=2 Boards=1 SocketsPerBoard=1 CoresPerSocket=2 ThreadsPerCore=1 RealMemory=24105"
    node_line="$(slurmd -C | head -n1)"  # its second line is UpTime=...
    [[ "$node_line" == NodeName=* ]] || die "unexpected 'slurmd -C' output: $node_line"
    mem="$(sed -n 's/.*RealMemory=\([0-9]*\).*/\1/p' <<<"$node_line")"
    mkdir -p "$(dirname "$SLURM_CONF_FILE")"
    cat >"$SLURM_CONF_FILE.tmp" <<EOF
$MARKER
# One node, controller and slurmd on 127.0.0.1; see the script's header for the choices.
ClusterName=local
SlurmctldHost=$hostname_short(127.0.0.1)
SlurmUser=slurm
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
StateSaveLocation=/var/lib/slurm/slurmctld
SlurmdSpoolDir=/var/lib/slurm/slurmd
SlurmctldPidFile=$CTLD_PID
SlurmdPidFile=$SLURMD_PID
SlurmctldLogFile=$LOG_DIR/slurmctld.log
SlurmdLogFile=$LOG_DIR/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/filetxt
JobCompLoc=$JOBCOMP_LOG
MinJobAge=600
ReturnToService=2
SlurmdTimeout=300
$node_line NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=$PARTITION Nodes=$hostname_short Default=YES MaxTime=INFINITE State=UP
EOF
    # Leave an identical file untouched.
    if [[ -e "$SLURM_CONF_FILE" ]] && cmp -s "$SLURM_CONF_FILE.tmp" "$SLURM_CONF_FILE"; then
        rm -f "$SLURM_CONF_FILE.tmp"
    else
        mv "$SLURM_CONF_FILE.tmp" "$SLURM_CONF_FILE"
        log "wrote $SLURM_CONF_FILE (node $hostname_short, ${mem} MB, partition $PARTITION)"
    fi
    mkdir -p /var/lib/slurm/slurmctld /var/lib/slurm/slurmd "$LOG_DIR"
    chown slurm:slurm /var/lib/slurm/slurmctld "$LOG_DIR"
    touch "$JOBCOMP_LOG"
    chown slurm:slurm "$JOBCOMP_LOG"
}

start_munge() {
    if running "$MUNGE_PID"; then
        return 0
    fi
    if [[ ! -s /etc/munge/munge.key ]]; then
        mungekey --create --keyfile /etc/munge/munge.key
        chown munge:munge /etc/munge/munge.key
        chmod 0400 /etc/munge/munge.key
    fi
    mkdir -p /run/munge /var/log/munge /var/lib/munge
    chown munge:munge /run/munge /var/log/munge /var/lib/munge
    log "starting munged"
    runuser -u munge -- /usr/sbin/munged
    munge -n | unmunge >/dev/null || die "munge round trip failed (see /var/log/munge/munged.log)"
}

start_daemons() {
    if ! running "$CTLD_PID"; then
        log "starting slurmctld"
        /usr/sbin/slurmctld || die "slurmctld failed to start (see $LOG_DIR/slurmctld.log)"
    fi
    if ! running "$SLURMD_PID"; then
        log "starting slurmd"
        /usr/sbin/slurmd || die "slurmd failed to start (see $LOG_DIR/slurmd.log)"
    fi
}

wait_idle() {
    local state="" i
    for i in $(seq 1 60); do
        state="$(sinfo -h -N -o %T 2>/dev/null | head -n1 || true)"
        case "$state" in
            idle | mixed | allocated | completing)
                log "node $state"
                return 0 ;;
            down* | drain* | drained*)
                # e.g. after an unclean stop; the config is ours, so resume it.
                scontrol update nodename="$(hostname -s)" state=resume 2>/dev/null || true ;;
        esac
        sleep 1
    done
    die "node not idle after 60 s (state: '${state:-no answer}'; see $LOG_DIR/slurmctld.log, $LOG_DIR/slurmd.log)"
}

stop_daemon() {
    local name="$1" pidfile="$2" pid i
    running "$pidfile" || return 0
    pid="$(cat "$pidfile")"
    log "stopping $name (pid $pid)"
    kill "$pid"
    for i in $(seq 1 30); do
        kill -0 "$pid" 2>/dev/null || return 0
        sleep 1
    done
    die "$name (pid $pid) did not stop within 30 s"
}

smoke() {
    local dir="${1:-}" start end
    sinfo -h >/dev/null 2>&1 || die "SLURM does not answer; run: bash $0 start"
    [[ $# -gt 0 ]] && shift
    [[ -n "$dir" ]] || dir="$(mktemp -d /tmp/slurm-smoke.XXXXXX)"
    mkdir -p "$dir"
    # The rules call the installed CLIs (python -m scenegen ...), so the workflow files suffice. Files
    # already in DIR are kept (e.g. a `git archive` snapshot run with PYTHONPATH=DIR).
    for name in Snakefile workflow config examples; do
        [[ -e "$dir/$name" ]] || cp -r "$REPO_ROOT/$name" "$dir/$name"
    done
    # shellcheck source=/dev/null
    source "$REPO_ROOT/scripts/setup.sh" >/dev/null 2>&1 || die "scripts/setup.sh failed"
    python -c 'import snakemake_executor_plugin_slurm' 2>/dev/null \
        || die "snakemake-executor-plugin-slurm missing: pip install -e '.[slurm]' (or the pin in pyproject.toml)"
    log "running the smoke config's renders + evaluate through SLURM in $dir"
    start="$(date +%s)"
    (cd "$dir" && snakemake renders evaluate --configfile config/smoke.yaml \
        --profile workflow/profiles/slurm $(slurm_overrides) "$@")
    end="$(date +%s)"
    log "finished in $((end - start)) s; per-job SLURM records: $JOBCOMP_LOG"
}

# Command-line options that point workflow/profiles/slurm at this one-node SLURM. --default-resources
# replaces the profile's whole default-resources mapping; that only drops defaults no job needs, since
# the profile's set-resources give every job rule its memory, wall time and CPUs
# (tests/test_workflow.py::test_slurm_profile_sets_resources_for_every_rule).
slurm_overrides() {
    echo "--default-resources slurm_partition=$PARTITION slurm_account=$ACCOUNT" \
        "--slurm-status-command squeue --slurm-init-seconds-before-status-checks 5 --latency-wait 5"
}

case "${1:-}" in
    start)
        install_packages
        write_config
        start_munge
        start_daemons
        wait_idle ;;
    stop)
        stop_daemon slurmd "$SLURMD_PID"
        stop_daemon slurmctld "$CTLD_PID"
        stop_daemon munged "$MUNGE_PID" ;;
    status)
        sinfo
        squeue ;;
    overrides)
        slurm_overrides ;;
    smoke)
        shift
        smoke "$@" ;;
    *)
        echo "usage: $0 start|stop|status|overrides|smoke [DIR] [snakemake args...]" >&2
        exit 2 ;;
esac
