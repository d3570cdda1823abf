#!/usr/bin/env bash
# A one-node Slurm cluster on this machine, for tests and trials (docs/slurm.md):
# munged, slurmctld and slurmd started in the foreground (no systemd), each in the
# background of this script with its standard streams redirected, its PID kept in
# $PERSIST_SLURM_DIR/pids/, and stopped by that PID.
#
#   scripts/slurm_cluster.sh install   install Debian's slurm-wlm and munge if missing
#   scripts/slurm_cluster.sh start     install if needed, start, wait for an idle node;
#                                      prints `export SLURM_CONF=...` for the clients
#   scripts/slurm_cluster.sh stop      stop the daemons this directory started
#
# Everything lives in PERSIST_SLURM_DIR (default /tmp/persist-slurm): configuration,
# munge key and socket, spool, logs, PIDs. The ports are private too (PERSIST_SLURM_PORT,
# default 16817, and the next one), so a cluster on the machine's standard ports is not
# touched. Needs root (the daemons switch users and launch jobs); fails loudly otherwise.
set -euo pipefail
DIR=${PERSIST_SLURM_DIR:-/tmp/persist-slurm}
PORT=${PERSIST_SLURM_PORT:-16817}
PIDS=$DIR/pids

die() { echo "slurm_cluster: $*" >&2; exit 1; }

install() {
  if command -v slurmctld >/dev/null 2>&1 && command -v slurmd >/dev/null 2>&1 \
     && command -v munged >/dev/null 2>&1 && command -v sbatch >/dev/null 2>&1; then
    return 0
  fi
  local sudo=""
  if [ "$(id -u)" -ne 0 ]; then sudo="sudo"; fi
  echo "slurm_cluster: installing slurm-wlm and munge" >&2
  export DEBIAN_FRONTEND=noninteractive
  $sudo apt-get update -qq
  $sudo apt-get install -y -qq --no-install-recommends slurm-wlm munge >/dev/null
}

# Is PID alive and running the program NAME?
alive() {
  local pid=$1 name=$2
  [ -n "$pid" ] && [ -r "/proc/$pid/comm" ] && [ "$(cat "/proc/$pid/comm" 2>/dev/null)" = "$name" ]
}

stop_one() {
  local name=$1 f=$PIDS/$1.pid pid
  [ -f "$f" ] || return 0
  pid=$(cat "$f")
  if alive "$pid" "$name"; then
    kill -TERM "$pid" 2>/dev/null || true
    for _ in $(seq 1 100); do alive "$pid" "$name" || break; sleep 0.1; done
    if alive "$pid" "$name"; then
      echo "slurm_cluster: $name ($pid) did not stop on TERM; KILL" >&2
      kill -KILL "$pid" 2>/dev/null || true
    fi
  fi
  rm -f "$f"
}

stop() {
  # reverse order of start
  stop_one slurmd
  stop_one slurmctld
  stop_one munged
}

start() {
  install
  [ "$(id -u)" -eq 0 ] || die "needs root: the daemons switch users and launch jobs (id -u = $(id -u))"
  stop
  local host mem cpus
  host=$(hostname -s)
  getent hosts "$host" >/dev/null || echo "127.0.0.1 $host" >>/etc/hosts
  mkdir -p "$DIR"/{munge,spool/ctld,spool/d,log} "$PIDS"
  chmod 755 "$DIR"
  rm -rf "$DIR"/spool/ctld/* "$DIR"/spool/d/*
  # munge: a fresh key, owned by the munge user, which runs munged
  if [ ! -s "$DIR/munge/munge.key" ]; then
    dd if=/dev/urandom of="$DIR/munge/munge.key" bs=1024 count=1 status=none
  fi
  chown -R munge:munge "$DIR/munge"
  chmod 700 "$DIR/munge"
  chmod 400 "$DIR/munge/munge.key"
  setpriv --reuid=munge --regid=munge --init-groups \
    munged --foreground --force \
      --socket="$DIR/munge/munge.socket" --key-file="$DIR/munge/munge.key" \
      --pid-file="$DIR/munge/munged.pid" --seed-file="$DIR/munge/munge.seed" \
      --log-file="$DIR/munge/munged.log" \
      </dev/null >"$DIR/log/munged.out" 2>&1 &
  echo $! >"$PIDS/munged.pid"
  for _ in $(seq 1 50); do [ -S "$DIR/munge/munge.socket" ] && break; sleep 0.1; done
  [ -S "$DIR/munge/munge.socket" ] || { cat "$DIR/log/munged.out" "$DIR/munge/munged.log" >&2 2>/dev/null || true; stop; die "munged did not start"; }
  cpus=$(nproc)
  mem=$(awk '/MemTotal/ { printf "%d", $2 / 1024 * 0.9 }' /proc/meminfo)
  cat >"$DIR/slurm.conf" <<CONF
ClusterName=persist
SlurmctldHost=$host
SlurmctldPort=$PORT
SlurmdPort=$((PORT + 1))
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$DIR/munge/munge.socket
StateSaveLocation=$DIR/spool/ctld
SlurmdSpoolDir=$DIR/spool/d
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/log/slurmctld.log
SlurmdLogFile=$DIR/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
SchedulerParameters=batch_sched_delay=0,sched_min_interval=0
DependencyParameters=kill_invalid_depend
ReturnToService=2
MpiDefault=none
SwitchType=switch/none
MinJobAge=600
NodeName=$host CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONF
  export SLURM_CONF=$DIR/slurm.conf
  slurmctld -D -i -f "$SLURM_CONF" </dev/null >"$DIR/log/slurmctld.out" 2>&1 &
  echo $! >"$PIDS/slurmctld.pid"
  slurmd -D -f "$SLURM_CONF" -N "$host" </dev/null >"$DIR/log/slurmd.out" 2>&1 &
  echo $! >"$PIDS/slurmd.pid"
  local state=""
  for _ in $(seq 1 300); do
    state=$(sinfo -h -n "$host" -o %T 2>/dev/null | head -1 || true)
    [ "$state" = "idle" ] && break
    sleep 0.1
  done
  if [ "$state" != "idle" ]; then
    echo "slurm_cluster: node state '${state}' after 30 s; logs:" >&2
    tail -n 20 "$DIR"/log/*.log "$DIR"/log/*.out >&2 2>/dev/null || true
    stop
    die "the cluster did not start"
  fi
  echo "export SLURM_CONF=$SLURM_CONF"
}

case "${1:-}" in
  install) install ;;
  start) start ;;
  stop) stop ;;
  *) die "usage: $0 install|start|stop" ;;
esac
