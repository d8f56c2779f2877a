#!/bin/bash
# A reproducible check of the sweep's SLURM path on this one machine (Debian 12, run as root):
# installs SLURM and munge from Debian if missing, starts a private single-node SLURM (its own
# config, spool and ports under $WORK; nothing in /etc/slurm is touched), then
#   A. workflows/slurm_cluster.py + `sweep run --scheduler`: an N-sample tiny-mesh sweep; one
#      worker job is scancel'ed mid-run; the cluster must replace it and the sweep must land
#      every sample exactly once;
#   B. `sbatch workflows/sweep.sbatch ...`: the same, with the driver itself a SLURM job;
#   D. `sbatch workflows/sweep.sbatch ...` cancelled mid-run (the driver gets SIGTERM): it must
#      print its summary and release its lock, leave no worker job behind, and the same line
#      resubmitted must finish the sweep, exactly once;
#   C. (LONG=1, default) one worker job with a 1-minute wall time and a sweep that outlasts it:
#      the worker retires before its wall time, a replacement job finishes the sweep;
# and stops everything it started.  Needs the repo's .venv with the slurm extra (make slurm).
#     workflows/slurm_check.sh                  # from the repository root
#     N=8 LONG=0 WORK=/tmp/sc workflows/slurm_check.sh
#     PARTS="A D" workflows/slurm_check.sh        # only some parts (default: A B D, and C with LONG=1)
set -euo pipefail
T0=$(date +%s)
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
WORK=${WORK:-/tmp/elastimap-slurm-check}
PY=$ROOT/.venv/bin/python
N=${N:-8}
LONG=${LONG:-1}
N_LONG=${N_LONG:-24}
PARTS=${PARTS:-A B D C}
want() { case " $PARTS " in *" $1 "*) return 0 ;; *) return 1 ;; esac; }
log() { echo "[slurm_check $(($(date +%s) - T0)) s] $*"; }
fail() { echo "slurm_check: FAIL: $*" >&2; exit 1; }

[ "$(id -u)" = 0 ] || fail "run as root (it installs and starts SLURM daemons)"
"$PY" -c "import dask_jobqueue" 2>/dev/null || fail "dask-jobqueue is missing from $ROOT/.venv: run make slurm"

# ------------------------------------------------------------------ install and start a one-node SLURM
if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null || ! command -v munged >/dev/null \
        || ! command -v sbatch >/dev/null; then
    log "installing slurmctld slurmd munge (apt-get)"
    apt-get update -q >/dev/null
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q slurmctld slurmd munge slurm-client >/dev/null
fi
rm -rf "$WORK"
mkdir -p "$WORK"/etc "$WORK"/spool/ctld "$WORK"/spool/d "$WORK"/log "$WORK"/sweeps
HOST=$(hostname -s)
MEM=$(free -m | awk '/^Mem:/ {print int($2 * 0.9)}')
PORT=${SLURM_CHECK_PORT:-16817}
cat >"$WORK/etc/slurm.conf" <<EOF
ClusterName=elastimapcheck
SlurmctldHost=$HOST(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$WORK/spool/ctld
SlurmdSpoolDir=$WORK/spool/d
SlurmctldPidFile=$WORK/slurmctld.pid
SlurmdPidFile=$WORK/slurmd.pid
SlurmctldLogFile=$WORK/log/slurmctld.log
SlurmdLogFile=$WORK/log/slurmd.log
SlurmctldPort=$PORT
SlurmdPort=$((PORT + 1))
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
SchedulerType=sched/backfill
ReturnToService=2
MpiDefault=none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SlurmdParameters=config_overrides
KillWait=10
MinJobAge=30
# more CPUs than the machine has: a driver job and several one-core worker jobs share 2 cores
NodeName=$HOST NodeAddr=127.0.0.1 CPUs=8 RealMemory=$MEM State=UNKNOWN
PartitionName=check Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
EOF
export SLURM_CONF=$WORK/etc/slurm.conf

STARTED_MUNGE=""
cleanup() {
    set +e
    [ -n "${CL_PID:-}" ] && kill "$CL_PID" 2>/dev/null && wait "$CL_PID" 2>/dev/null
    [ -n "${DRV_PID:-}" ] && kill "$DRV_PID" 2>/dev/null && wait "$DRV_PID" 2>/dev/null
    if [ -s "$WORK/slurmctld.pid" ]; then
        scancel --partition check 2>/dev/null
        sleep 2
    fi
    for f in "$WORK/slurmd.pid" "$WORK/slurmctld.pid"; do
        [ -s "$f" ] && kill "$(cat "$f")" 2>/dev/null
    done
    [ -n "$STARTED_MUNGE" ] && kill "$STARTED_MUNGE" 2>/dev/null
    log "stopped the daemons this script started; logs under $WORK/log"
}
trap cleanup EXIT

if ! munge -n >/dev/null 2>&1; then
    mkdir -p /run/munge /var/log/munge /var/lib/munge
    chown munge:munge /run/munge /var/log/munge /var/lib/munge
    [ -s /etc/munge/munge.key ] || { dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=1024 2>/dev/null;
                                     chown munge:munge /etc/munge/munge.key; chmod 400 /etc/munge/munge.key; }
    runuser -u munge -- /usr/sbin/munged
    sleep 1
    STARTED_MUNGE=$(cat /run/munge/munged.pid)
    munge -n >/dev/null || fail "munged does not answer"
fi
slurmctld -f "$SLURM_CONF"
slurmd -f "$SLURM_CONF"
for _ in $(seq 60); do
    state=$(sinfo -h -o %t 2>/dev/null || true)
    [ "$state" = idle ] && break
    sleep 1
done
[ "$state" = idle ] || fail "the SLURM node did not come up (state '$state'; see $WORK/log)"
log "SLURM up: node $HOST, partition check"

# ------------------------------------------------------------------ helpers
landed() { ls "$1" 2>/dev/null | grep -c '^[rb]-.*\.parquet$' || true; }
wait_rows() {  # DIR K PID: until K rows landed (while PID lives)
    for _ in $(seq 600); do
        [ "$(landed "$1")" -ge "$2" ] && return 0
        kill -0 "$3" 2>/dev/null || return 1
        sleep 0.5
    done
    return 1
}
cancel_one_worker() {
    local job
    job=$(squeue -h -n dask-worker -t R -o %i | head -1)
    [ -n "$job" ] || fail "no running worker job to cancel"
    scancel "$job"
    log "scancel worker job $job mid-run ($(landed "$1") rows landed)"
}
exactly_once() {  # DIR N: every planned id landed exactly once (raw rows, all files), all ok
    "$PY" - "$1" "$2" <<'PYEOF'
import collections, sys
from pathlib import Path
import pyarrow.parquet as pq
from elastimap.dataset import io
out, n = Path(sys.argv[1]), int(sys.argv[2])
ids, status = [], {}
for f in sorted(out.glob("*.parquet")):
    t = pq.read_table(f, columns=["sample_id", "status"]).to_pydict()
    ids += t["sample_id"]
    status.update(zip(t["sample_id"], t["status"]))
planned = io.read_manifest(out)["planned"]
twice = [k for k, c in collections.Counter(ids).items() if c > 1]
missing = set(planned) - set(ids)
bad = [k for k, v in status.items() if v != "ok"]
print(f"  {out.name}: {len(ids)} rows, {len(set(ids))} ids, planned {len(planned)}, twice {len(twice)}, "
      f"missing {len(missing)}, not ok {len(bad)}")
sys.exit(0 if len(planned) == n and not twice and not missing and not bad and len(ids) == n else 1)
PYEOF
}
start_cluster() {  # NAME WORKERS WALLTIME: slurm_cluster.py in the background, wait for its address file
    local addr=$WORK/scheduler.$1
    "$PY" workflows/slurm_cluster.py --workers "$2" --walltime "$3" --memory 2GiB --address-file "$addr" \
        --log-dir "$WORK/log" --dashboard :0 --interface lo >"$WORK/log/cluster-$1.log" 2>&1 &
    CL_PID=$!
    for _ in $(seq 300); do
        [ -s "$addr" ] && break
        kill -0 "$CL_PID" 2>/dev/null || fail "slurm_cluster.py ended early: $(tail -3 "$WORK/log/cluster-$1.log")"
        sleep 1
    done
    [ -s "$addr" ] || fail "no cluster address after 300 s"
    ADDR=$(cat "$addr")
    log "cluster $1 up at $ADDR ($2 worker job(s), wall time $3)"
}
stop_cluster() {  # NAME
    kill -TERM "$CL_PID"
    wait "$CL_PID" || true
    CL_PID=""
    [ ! -e "$WORK/scheduler.$1" ] || fail "slurm_cluster.py left its address file behind"
    grep -q "replaced job" "$WORK/log/cluster-$1.log" || fail "the cluster never replaced a worker job (see cluster-$1.log)"
    log "cluster $1 stopped; $(grep -o 'replaced job.*' "$WORK/log/cluster-$1.log" | tr '\n' ' ')"
}

# ------------------------------------------------------------------ A: slurm_cluster.py + sweep run --scheduler
if want A; then
tA=$(date +%s)
start_cluster a 2 00:10:00
OUT=$WORK/sweeps/a
"$PY" -m elastimap.sweep.cli run --n "$N" --mesh tiny --seed 11 --out "$OUT" --no-progress --scheduler "$ADDR" \
    >"$WORK/log/sweep-a.log" 2>&1 &
DRV_PID=$!
wait_rows "$OUT" 2 "$DRV_PID" || fail "A: no rows landed ($(tail -3 "$WORK/log/sweep-a.log"))"
cancel_one_worker "$OUT"
rc=0
wait "$DRV_PID" || rc=$?
DRV_PID=""
[ "$rc" = 0 ] || fail "A: sweep exited $rc: $(tail -5 "$WORK/log/sweep-a.log")"
grep "sweep:\|dataset:" "$WORK/log/sweep-a.log" | sed 's/^/  /'
exactly_once "$OUT" "$N" || fail "A: not exactly once"
for _ in $(seq 30); do grep -q "replaced job" "$WORK/log/cluster-a.log" && break; sleep 1; done
stop_cluster a
log "A passed in $(($(date +%s) - tA)) s"
fi

# ------------------------------------------------------------------ B: sbatch workflows/sweep.sbatch
submit() {  # NAME SEED: sbatch workflows/sweep.sbatch for an N-sample tiny sweep into $WORK/sweeps/NAME
    WORKERS=2 WORKER_WALLTIME=00:10:00 WORKER_MEMORY=2GiB WORKER_LOG_DIR=$WORK/log INTERFACE=lo \
        sbatch --parsable -D "$ROOT" -o "$WORK/log/sweep-$1-%j.log" workflows/sweep.sbatch \
        --n "$N" --mesh tiny --seed "$2" --out "$WORK/sweeps/$1"
}
alive() { squeue -h -j "$JOB" -o %i 2>/dev/null | grep -q .; }
wait_job_rows() {  # PART: until 2 rows landed while $JOB runs
    for _ in $(seq 600); do
        [ "$(landed "$OUT")" -ge 2 ] && return 0
        alive || fail "$1: job $JOB ended early: $(tail -5 "$WORK/log/sweep-$2-$JOB.log")"
        sleep 0.5
    done
    fail "$1: no rows landed"
}
wait_job_end() {  # PART
    for _ in $(seq 600); do alive || return 0; sleep 1; done
    fail "$1: job $JOB still running after 600 s"
}
no_leftovers() {  # PART
    [ -z "$(squeue -h -n dask-worker -o %i)" ] || { sleep 15; [ -z "$(squeue -h -n dask-worker -o %i)" ] \
        || fail "$1: worker jobs left after the sweep job ended"; }
    if ls "$ROOT"/scheduler.* >/dev/null 2>&1; then fail "$1: an address file was left in $ROOT"; fi
}
if want B; then
tB=$(date +%s)
OUT=$WORK/sweeps/b
JOB=$(submit b 12)
log "B: submitted workflows/sweep.sbatch as job $JOB"
wait_job_rows B b
cancel_one_worker "$OUT"
wait_job_end B
grep "sweep:\|dataset:" "$WORK/log/sweep-b-$JOB.log" | sed 's/^/  /' || true
grep -q "done this run" "$WORK/log/sweep-b-$JOB.log" || fail "B: no summary: $(tail -5 "$WORK/log/sweep-b-$JOB.log")"
exactly_once "$OUT" "$N" || fail "B: not exactly once"
no_leftovers B
log "B passed in $(($(date +%s) - tB)) s"
fi

# ------------------------------------------------------------------ D: the sweep job cancelled, then resubmitted
if want D; then
tD=$(date +%s)
OUT=$WORK/sweeps/d
JOB=$(submit d 14)
log "D: submitted workflows/sweep.sbatch as job $JOB"
wait_job_rows D d
scancel "$JOB"
log "D: scancel sweep job $JOB mid-run ($(landed "$OUT") rows landed)"
wait_job_end D
LOG1=$WORK/log/sweep-d-$JOB.log
grep -q "interrupted by SIGTERM" "$LOG1" || fail "D: the driver did not handle SIGTERM: $(tail -5 "$LOG1")"
grep -q "done this run" "$LOG1" || fail "D: no summary after SIGTERM"
[ ! -e "$OUT/.sweep.lock" ] || fail "D: the cancelled driver left its lock"
if ls "$OUT"/.attempts-* >/dev/null 2>&1; then fail "D: the cancelled driver left attempt markers"; fi
no_leftovers D
first=$(landed "$OUT")
JOB=$(submit d 14)
log "D: $first rows kept; resubmitted the same line as job $JOB"
wait_job_end D
grep "sweep:\|dataset:" "$WORK/log/sweep-d-$JOB.log" | sed 's/^/  /' || true
grep -q "skipped (already landed)" "$WORK/log/sweep-d-$JOB.log" || fail "D: resubmitted job: $(tail -5 "$WORK/log/sweep-d-$JOB.log")"
exactly_once "$OUT" "$N" || fail "D: not exactly once"
log "D passed in $(($(date +%s) - tD)) s"
fi

# ------------------------------------------------------------------ C: a sweep longer than a worker's wall time
if [ "$LONG" = 1 ] && want C; then
    tC=$(date +%s)
    start_cluster c 1 00:01:00
    OUT=$WORK/sweeps/c
    rc=0
    "$PY" -m elastimap.sweep.cli run --n "$N_LONG" --mesh tiny --seed 13 --out "$OUT" --no-progress \
        --scheduler "$ADDR" --worker-wait 300 >"$WORK/log/sweep-c.log" 2>&1 || rc=$?
    [ "$rc" = 0 ] || fail "C: sweep exited $rc: $(tail -5 "$WORK/log/sweep-c.log")"
    grep "sweep:\|dataset:" "$WORK/log/sweep-c.log" | sed 's/^/  /'
    exactly_once "$OUT" "$N_LONG" || fail "C: not exactly once"
    stop_cluster c
    log "C passed in $(($(date +%s) - tC)) s (a 1-minute worker wall time)"
fi
log "PASS: parts $PARTS$([ "$LONG" = 1 ] || echo ' (C skipped: LONG=0)'): every sample landed exactly once"
