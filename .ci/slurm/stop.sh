#!/usr/bin/env bash
# Stop the daemons .ci/slurm/start.sh started (slurmd, slurmctld), by their PID files.
# munged is left running (other tools may use it); its PID is in /run/munge/munged.pid.
set -euo pipefail
DIR=${BGS_SLURM_DIR:-/var/tmp/bgs-slurm}
WAIT_TICKS=100   # × 0.1 s

for daemon in slurmd slurmctld; do
    pidfile=$DIR/$daemon.pid
    if [ -s "$pidfile" ] && kill -0 "$(cat "$pidfile")" 2>/dev/null; then
        pid=$(cat "$pidfile")
        kill "$pid"
        for _ in $(seq $WAIT_TICKS); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
        echo "slurm/stop.sh: stopped $daemon ($pid)"
    fi
done
