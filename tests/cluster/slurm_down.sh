#!/usr/bin/env bash
# Stop the daemons tests/cluster/slurm_up.sh started (listed in $STATE/started), newest first, by their
# pid files; daemons it found already running are left alone. The accounting database stays, so the next
# slurm_up.sh is quick; the generated slurm.conf goes with the controller.
set -uo pipefail
STATE=${RIGBUILD_SLURM_DIR:-/var/lib/rigbuild-slurm}
[ -s "$STATE/started" ] || { echo "slurm_down: nothing started by slurm_up.sh"; exit 0; }
pidfile() {
  case "$1" in
    slurmd|slurmctld|slurmdbd) echo "$STATE/run/$1.pid" ;;
    mariadb) echo /run/mysqld/rigbuild-mysqld.pid ;;
    munged) echo /run/munge/munged.pid ;;
  esac
}
for d in $(tac "$STATE/started"); do
  f=$(pidfile "$d")
  [ -n "$f" ] && [ -s "$f" ] || continue
  pid=$(cat "$f")
  kill -0 "$pid" 2>/dev/null || continue
  echo "slurm_down: stopping $d ($pid)"
  kill "$pid"
  for _ in $(seq 40); do kill -0 "$pid" 2>/dev/null || break; sleep 0.25; done
  kill -0 "$pid" 2>/dev/null && { echo "slurm_down: $d ($pid) still running; sending KILL"; kill -9 "$pid"; }
done
# a slurm.conf whose controller is down makes every scontrol wait ~9 s for it, and snakemake's SLURM plugin
# runs `scontrol show config` whenever snakemake starts: the generated one goes with the controller
# (slurm_up.sh writes it again)
CONF=/etc/slurm/slurm.conf
if grep -qx slurmctld "$STATE/started" && [ -e "$CONF" ] && grep -qF "# rigbuild one-node test cluster" "$CONF"; then
  rm -f "$CONF"
fi
rm -f "$STATE/started"
