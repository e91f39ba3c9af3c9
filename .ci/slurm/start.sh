#!/usr/bin/env bash
# Start a single-node Slurm (munge, slurmctld, slurmd) on localhost, as root, without systemd.
#
#   .ci/slurm/start.sh          # idempotent: daemons already running are left alone
#   .ci/slurm/stop.sh           # stops the daemons this script started (by their PID files)
#
# Everything lives in $BGS_SLURM_DIR (default /var/tmp/bgs-slurm): slurm.conf, state, spool,
# logs, PID files. The node's CPUs and memory come from `slurmd -C`. /etc/slurm/slurm.conf is
# linked to the generated file when nothing else is there, so sbatch/squeue/scontrol find the
# cluster without SLURM_CONF; otherwise export SLURM_CONF=$BGS_SLURM_DIR/slurm.conf.
# Needs the Debian packages slurmctld slurmd slurm-client munge (.ci/run installs them).
set -euo pipefail

DIR=${BGS_SLURM_DIR:-/var/tmp/bgs-slurm}
TIMEOUT=${BGS_SLURM_TIMEOUT:-60}   # seconds to wait for the node to become idle
CRED_EXPIRE=10                     # s; a requeued job is held this long (Slurm default 120)
SCHED_INTERVAL=2                   # s between main scheduling passes (Slurm default 60)
MIN_JOB_AGE=30                     # s a finished job stays visible in squeue (default 300)
TEMPLATE="$(cd "$(dirname "$0")" && pwd)/slurm.conf.in"
CONF=$DIR/slurm.conf
SYSTEM_CONF=/etc/slurm/slurm.conf

die() { echo "slurm/start.sh: $*" >&2; exit 1; }

[ "$(id -u)" -eq 0 ] || die "must run as root (slurmd and munged are started directly)"
for tool in munged slurmctld slurmd sinfo scontrol; do
    command -v "$tool" >/dev/null || die "$tool not found: apt-get install slurmctld slurmd slurm-client munge"
done

alive() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

# --- munge: the package created /etc/munge/munge.key; munged must run as the munge user
if ! munge -n </dev/null 2>/dev/null | unmunge >/dev/null 2>&1; then
    install -d -o munge -g munge -m 0755 /run/munge
    install -d -o munge -g munge -m 0700 /var/log/munge /var/lib/munge
    [ -f /etc/munge/munge.key ] || die "/etc/munge/munge.key is missing: reinstall munge or run mungekey"
    runuser -u munge -- munged || die "munged did not start (see /var/log/munge/munged.log)"
    for _ in $(seq 50); do
        munge -n </dev/null 2>/dev/null | unmunge >/dev/null 2>&1 && break
        sleep 0.1
    done
    munge -n </dev/null | unmunge >/dev/null || die "munge does not answer (see /var/log/munge/munged.log)"
fi

# --- slurm.conf from the template, with this machine's node line
mkdir -p "$DIR/state" "$DIR/spool" "$DIR/log"
node=$(slurmd -C | head -n 1)          # NodeName=<host> CPUs=… Boards=… … RealMemory=…
host=${node#NodeName=}
host=${host%% *}
sed -e "s|@HOST@|$host|g" -e "s|@DIR@|$DIR|g" -e "s|@NODE@|$node|" \
    -e "s|@CRED_EXPIRE@|$CRED_EXPIRE|" -e "s|@SCHED_INTERVAL@|$SCHED_INTERVAL|g" \
    -e "s|@MIN_JOB_AGE@|$MIN_JOB_AGE|" "$TEMPLATE" >"$CONF.tmp"
mv "$CONF.tmp" "$CONF"
export SLURM_CONF=$CONF
if [ ! -e "$SYSTEM_CONF" ] || [ "$(readlink "$SYSTEM_CONF")" = "$CONF" ]; then
    mkdir -p "$(dirname "$SYSTEM_CONF")"
    ln -sfn "$CONF" "$SYSTEM_CONF"
else
    echo "slurm/start.sh: $SYSTEM_CONF exists and is not ours; use: export SLURM_CONF=$CONF" >&2
fi

# --- daemons (each one only when its PID file names no live process)
alive "$DIR/slurmctld.pid" || slurmctld -f "$CONF" || die "slurmctld did not start (see $DIR/log/slurmctld.log)"
alive "$DIR/slurmd.pid" || slurmd -f "$CONF" || die "slurmd did not start (see $DIR/log/slurmd.log)"

# --- wait for the node to be usable; a node left down/drained by an earlier run is resumed
deadline=$((SECONDS + TIMEOUT))
resumed=no
while :; do
    state=$(sinfo -h -n "$host" -o %T 2>/dev/null || true)
    case "$state" in
        idle | mixed | allocated | completing) break ;;
        *drain* | down*)
            if [ $resumed = no ]; then
                scontrol update NodeName="$host" State=RESUME 2>/dev/null || true
                resumed=yes
            fi ;;
    esac
    if [ $SECONDS -ge $deadline ]; then
        echo "slurm/start.sh: node $host not idle after ${TIMEOUT}s (sinfo state: '${state:-no answer}')" >&2
        tail -n 5 "$DIR/log/slurmctld.log" "$DIR/log/slurmd.log" >&2 || true
        exit 1
    fi
    sleep 0.5
done
echo "slurm/start.sh: single-node Slurm up: node $host $state, SLURM_CONF=$CONF"
