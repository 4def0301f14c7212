#!/usr/bin/env bash
# A one-node Slurm cluster on this machine, started by hand (no systemd, no
# files in /etc): our own munged, slurmctld and slurmd, with every state,
# spool, pid and log file in DIR, configured by deploy/slurm/slurm.conf.
# docs/batch.md tries its job array on it; twin/cli/tests/it/batch.rs runs
# that array on it.
#
#   deploy/slurm/one-node.sh start DIR   stops what an earlier start in DIR
#                                        left running, empties DIR, starts the
#                                        cluster and waits until its node is
#                                        idle; then prints the SLURM_CONF to use
#   deploy/slurm/one-node.sh stop DIR    stops every process started in DIR,
#                                        found by the mark in its environment,
#                                        so even one whose pid file is gone
#
# SLURMCTLD_PORT and SLURMD_PORT choose the daemons' ports (default Slurm's,
# 6817 and 6818).
#
# Needs Debian's slurmctld, slurmd, slurm-client and munge (the packages;
# their services need not run). Run as root, jobs run as whoever submits
# them; as another user, the daemons run as that user and only their jobs run.
set -euo pipefail

usage() {
  echo "usage: $0 start|stop DIR" >&2
  exit 2
}
[ $# -eq 2 ] || usage
action=$1
mkdir -p "$2"
dir=$(cd "$2" && pwd)
here=$(cd "$(dirname "$0")" && pwd)
# Slurm's own ports unless told otherwise, as on a real cluster; another
# pair where a Slurm of the machine's own already has them.
ctld_port=${SLURMCTLD_PORT:-6817}
slurmd_port=${SLURMD_PORT:-6818}
# Every process this script starts carries this in its environment (so do
# slurmd's slurmstepd, which inherit it): `stop` finds them by it.
mark="TWIN_ONE_NODE_SLURM=$dir"

# The pids of the processes whose environment holds the mark.
marked() {
  grep --files-with-matches --null-data --line-regexp --fixed-strings "$mark" \
    /proc/[0-9]*/environ 2>/dev/null | sed -e 's|^/proc/||' -e 's|/environ$||' | grep -vx "$$" || true
}

stop() {
  # Jobs still running are cancelled while the controller still answers.
  if [ -e "$dir/slurm.conf" ] && [ -n "$(marked)" ]; then
    SLURM_CONF="$dir/slurm.conf" timeout 10 scancel --quiet --user="$(id -un)" 2>/dev/null || true
  fi
  local pids left tries=0
  pids=$(marked)
  [ -n "$pids" ] || return 0
  # shellcheck disable=SC2086 # one word per pid
  kill -TERM $pids 2>/dev/null || true
  # Up to 10 s to end on their own, then killed.
  while left=$(marked) && [ -n "$left" ] && [ $tries -lt 50 ]; do
    sleep 0.2
    tries=$((tries + 1))
  done
  if [ -n "$left" ]; then
    # shellcheck disable=SC2086
    kill -KILL $left 2>/dev/null || true
  fi
}

# The last lines of every log, when something did not come up.
logs() {
  local f
  for f in "$dir"/log/*; do
    echo "== $f" >&2
    tail -n 20 "$f" >&2
  done
}

start() {
  local need
  for need in munged mungekey slurmctld slurmd sinfo; do
    command -v "$need" >/dev/null || {
      echo "$0: $need is missing (Debian: apt-get install slurmctld slurmd slurm-client munge)" >&2
      exit 1
    }
  done
  stop
  rm -rf "${dir:?}"/*
  # munged wants its key readable by its user alone, and its socket's folder
  # open to everyone (a job's user must reach it).
  mkdir -p "$dir"/{munge,run,log,ctld,spool}
  chmod 700 "$dir/munge"
  chmod 755 "$dir" "$dir/run"
  mungekey --create --keyfile="$dir/munge/munge.key"

  local node user
  node=$(slurmd -C | head -n 1)
  user=$(id -un)
  sed -e "s|@HOST@|$(hostname -s)|g" -e "s|@USER@|$user|g" -e "s|@DIR@|$dir|g" \
    -e "s|@NODE@|$node|g" -e "s|@CTLD_PORT@|$ctld_port|g" -e "s|@SLURMD_PORT@|$slurmd_port|g" \
    "$here/slurm.conf" >"$dir/slurm.conf"
  export SLURM_CONF="$dir/slurm.conf"

  # In the foreground (-F, -D) of background jobs: no daemon forks away,
  # so each one's pid is its job's. -i: slurmctld starts without the state
  # files it has not written yet.
  env "$mark" munged -F --socket="$dir/run/munge.socket" --key-file="$dir/munge/munge.key" \
    --pid-file="$dir/run/munged.pid" --seed-file="$dir/munge/munged.seed" \
    >>"$dir/log/munged.log" 2>&1 </dev/null &
  local tries=0
  until [ -S "$dir/run/munge.socket" ]; do
    tries=$((tries + 1))
    if [ $tries -gt 100 ]; then
      echo "$0: munged did not start" >&2
      logs
      stop
      exit 1
    fi
    sleep 0.1
  done
  env "$mark" slurmctld -D -i >>"$dir/log/slurmctld.out" 2>&1 </dev/null &
  local ctld=$!
  env "$mark" slurmd -D >>"$dir/log/slurmd.out" 2>&1 </dev/null &
  local slurmd=$!

  # Up to 30 s for slurmd to register and its node to be idle; at once
  # if a daemon ended (a port taken, a wrong line in slurm.conf).
  tries=0
  until [ "$(sinfo --noheader --Node --format=%T 2>/dev/null)" = idle ]; do
    tries=$((tries + 1))
    local ended=""
    kill -0 $ctld 2>/dev/null || ended="slurmctld"
    kill -0 $slurmd 2>/dev/null || ended="$ended slurmd"
    if [ -n "$ended" ] || [ $tries -gt 150 ]; then
      echo "$0: the node did not become idle${ended:+ ($ended ended)}; sinfo says:" >&2
      sinfo --Node >&2 || true
      logs
      stop
      exit 1
    fi
    sleep 0.2
  done
  echo "SLURM_CONF=$SLURM_CONF"
}

case $action in
  start) start ;;
  stop) stop ;;
  *) usage ;;
esac
