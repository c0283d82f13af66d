#!/usr/bin/env bash
# Start a one-node SLURM cluster on this machine (idempotent): munged, MariaDB + slurmdbd (so `sacct`
# answers from a real accounting database), slurmctld and slurmd, with a slurm.conf generated for this
# host (2 CPUs, its real memory, one partition `cpu` as workflow/profiles/slurm names it).
#   tests/cluster/slurm_up.sh           # start (installs nothing; `make cluster-deps` installs the packages)
#   tests/cluster/slurm_down.sh         # stop what this script started
# Runs as root. Exit 77: this machine cannot host the cluster (not root, or SLURM not installed).
# Container-friendly plugins (no systemd, no cgroup delegation): proctrack/linuxproc, task/none,
# jobacct_gather/linux.
set -euo pipefail

STATE=${RIGBUILD_SLURM_DIR:-/var/lib/rigbuild-slurm}
CONF=/etc/slurm/slurm.conf
DBDCONF=/etc/slurm/slurmdbd.conf
MARK="# rigbuild one-node test cluster (tests/cluster/slurm_up.sh)"
NCPU=${RIGBUILD_SLURM_CPUS:-2}

log() { echo "slurm_up: $*"; }
# the daemons this script started, one a line: slurm_down.sh stops only those
started() { echo "$1" >>"$STATE/started"; }
die() { echo "slurm_up: error: $*" >&2; exit 1; }

[ "$(id -u)" = 0 ] || { echo "slurm_up: needs root (starts munged, slurmdbd, slurmctld, slurmd)" >&2; exit 77; }
for b in munged slurmctld slurmd slurmdbd mariadbd sbatch sacct; do
  command -v "$b" >/dev/null || { echo "slurm_up: $b not installed; run: make cluster-deps" >&2; exit 77; }
done
for f in "$CONF" "$DBDCONF"; do
  if [ -e "$f" ] && ! grep -qF "$MARK" "$f"; then
    die "$f exists and was not written by this script: this machine has its own SLURM; not touching it"
  fi
done

host=$(hostname -s)
mkdir -p "$STATE"/{ctld,spool,log,run}
chown slurm:slurm "$STATE" "$STATE"/{ctld,spool,log,run}

# --- munge: one key shared by every daemon on this single host
mkdir -p /run/munge /var/log/munge /var/lib/munge
chown munge:munge /run/munge /var/log/munge /var/lib/munge
if [ ! -s /etc/munge/munge.key ]; then
  mungekey --create --keyfile /etc/munge/munge.key
  chown munge:munge /etc/munge/munge.key; chmod 400 /etc/munge/munge.key
fi
if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
  log "starting munged"; started munged
  runuser -u munge -- /usr/sbin/munged
  for _ in $(seq 20); do munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break; sleep 0.5; done
  munge -n | unmunge >/dev/null || die "munged does not answer (see /var/log/munge/munged.log)"
fi

# --- MariaDB on a unix socket only (no TCP port), database and user for slurmdbd
# Debian's default socket, which libmariadb (slurmdbd) finds for StorageHost=localhost
SOCK=/run/mysqld/mysqld.sock
mkdir -p /run/mysqld; chown mysql:mysql /run/mysqld
if ! mariadb --socket="$SOCK" -e 'select 1' >/dev/null 2>&1; then
  [ -d /var/lib/mysql/mysql ] || mariadb-install-db --user=mysql --datadir=/var/lib/mysql >/dev/null
  log "starting MariaDB (socket $SOCK)"; started mariadb
  mariadbd --user=mysql --datadir=/var/lib/mysql --socket="$SOCK" --pid-file=/run/mysqld/rigbuild-mysqld.pid \
    --skip-networking --innodb-buffer-pool-size=64M --log-error="$STATE/log/mariadb.log" >/dev/null 2>&1 &
  for _ in $(seq 60); do mariadb --socket="$SOCK" -e 'select 1' >/dev/null 2>&1 && break; sleep 0.5; done
  mariadb --socket="$SOCK" -e 'select 1' >/dev/null || die "MariaDB did not start (see $STATE/log/mariadb.log)"
fi
mariadb --socket="$SOCK" -e "CREATE DATABASE IF NOT EXISTS slurm_acct_db;
  CREATE USER IF NOT EXISTS 'slurm'@'localhost' IDENTIFIED BY 'rigbuild-test';
  GRANT ALL ON slurm_acct_db.* TO 'slurm'@'localhost'; FLUSH PRIVILEGES;"

# --- configuration for this host
mem=$(slurmd -C | sed -n 's/.*RealMemory=\([0-9]*\).*/\1/p')
[ -n "$mem" ] || die "slurmd -C reported no RealMemory"
cat >"$DBDCONF.tmp" <<EOF
$MARK
AuthType=auth/munge
DbdHost=localhost
SlurmUser=slurm
LogFile=$STATE/log/slurmdbd.log
PidFile=$STATE/run/slurmdbd.pid
StorageType=accounting_storage/mysql
StorageHost=localhost
StorageLoc=slurm_acct_db
StorageUser=slurm
StoragePass=rigbuild-test
EOF
chown slurm:slurm "$DBDCONF.tmp"; chmod 600 "$DBDCONF.tmp"; mv "$DBDCONF.tmp" "$DBDCONF"

cat >"$CONF.tmp" <<EOF
$MARK
ClusterName=rigbuild
SlurmctldHost=$host(localhost)
SlurmUser=slurm
AuthType=auth/munge
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/spool
SlurmctldPidFile=$STATE/run/slurmctld.pid
SlurmdPidFile=$STATE/run/slurmd.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd.log
# no systemd or cgroup delegation in a container: track job processes by parent pid, no task binding
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/linux
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
# sacct shows the rule of each job (the plugin puts it in the job comment)
AccountingStoreFlags=job_comment
JobCompType=jobcomp/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
# the node keeps the CPUs declared here even on a bigger machine
SlurmdParameters=config_overrides
ReturnToService=2
MinJobAge=300
NodeName=$host NodeAddr=localhost CPUs=$NCPU RealMemory=$mem State=UNKNOWN
PartitionName=cpu Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
changed=0; cmp -s "$CONF.tmp" "$CONF" || changed=1
mv "$CONF.tmp" "$CONF"

pid_alive() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

if ! pid_alive "$STATE/run/slurmdbd.pid"; then
  log "starting slurmdbd"; started slurmdbd
  slurmdbd
  for _ in $(seq 60); do sacctmgr -n list cluster >/dev/null 2>&1 && break; sleep 0.5; done
  sacctmgr -n list cluster >/dev/null || die "slurmdbd does not answer (see $STATE/log/slurmdbd.log)"
fi
sacctmgr -n list cluster format=cluster%30 | grep -qw rigbuild || sacctmgr -i add cluster rigbuild >/dev/null
if ! pid_alive "$STATE/run/slurmctld.pid"; then
  log "starting slurmctld"; started slurmctld
  slurmctld
fi
# daemons already running read a changed slurm.conf again
if [ "$changed" = 1 ] && pid_alive "$STATE/run/slurmctld.pid"; then
  log "slurm.conf changed: scontrol reconfigure"; scontrol reconfigure
fi
if ! pid_alive "$STATE/run/slurmd.pid"; then
  log "starting slurmd"; started slurmd
  slurmd
fi
for _ in $(seq 60); do
  st=$(sinfo -h -n "$host" -o %T 2>/dev/null || true)
  case "$st" in idle*|mixed*|allocated*) break ;; esac
  sleep 0.5
done
case "$st" in
  idle*|mixed*|allocated*) ;;
  *) scontrol update nodename="$host" state=resume >/dev/null 2>&1 || true; sleep 1
     st=$(sinfo -h -n "$host" -o %T 2>/dev/null || true)
     case "$st" in
       idle*|mixed*|allocated*) ;;
       *) die "node $host is '$st' (see $STATE/log/slurmd.log, slurmctld.log)" ;;
     esac ;;
esac
log "cluster rigbuild up: node $host, $NCPU CPUs, ${mem} MB, partition cpu ($st)"
