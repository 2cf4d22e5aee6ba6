#!/usr/bin/env bash
# One lease of a lent GPU machine, planned to end inside its 10-minute call.
#
# Run from the repository root on the device machine (docs/performance.md, "On a GPU"):
#   bash benchmarks/gpu_lease.sh DATA_DIR [PLAN]
# DATA_DIR holds the real COM 1093 level-2 files of AB Dor (obs 12) and HD 37093 (obs 15);
# the machine has no network, so amigo runs from ./src with the packages its image lacks
# installed from wheels in ./.whl (astropy, pyerfa, astropy-iers-data, svo-filters, and
# py-spy for the sampled profile). Everything it measures lands in $OUT.
#
# PLAN batches (the default): where a warm `amigo fit` spends its time on a GPU, and how
# many Jacobian columns a step should push:
#   lease.log       every step's output, each stderr line stamped with seconds since start
#   batch.txt       benchmarks/jacobian_batch.py's table (batches 8, 256, 64 in that order; F480M)
#   fit_warm.spy    py-spy's samples (--idle: waiting counted) of a warm fit, fresh process
#   detect_warm.spy the same for a warm `amigo detect` of that fit's products
# PLAN profile: two measurements side by side, each its own process (the machine has 16
# CPU cores for XLA's compiler and one GPU; the training takes a fifth of its memory, the
# commands JAX's default share). Both read their files under $AMIGO_SHARED (data/jwst/
# com1093 and com1093-calibrators, copied into a carried folder), as on this machine:
#   train.log       benchmarks/train.py on the calibrators (AMIGO_SHARED must hold
#                   data/jwst/com1093-calibrators): seconds per epoch and per step
#   profile.log     benchmarks/profile_fit.py --platform any --runs both: the stages of a
#                   cold and a warm `amigo fit` + `amigo detect` of the three filters, with
#                   the latent bases of $SEED (if set) already in the cold cache, and the
#                   results against $REFERENCE (if set: an output folder of the same
#                   commands elsewhere, its fit_summary.json and detect/companions.json)
# PLAN spy: where a warm three-filter fit and detection spend their time, and NUTS on the
# host beside the GPU (AMIGO_SAMPLER_DEVICE=host):
#   profile.log     benchmarks/profile_fit.py --platform any --runs both --spy: the stages
#                   of a cold and a warm `amigo fit` + `amigo detect` (NUTS on), the warm
#                   ones sampled by py-spy
#   warm_fit.spy, warm_detect.spy   py-spy's samples (--idle, 50 Hz, raw folded stacks)
#   lease.log       then `amigo detect` on the same products with the chains on the host,
#                   twice (the first compiles their CPU programs), and once more with the
#                   chains on the GPU: each line stamped, /usr/bin/time's wall and peak
# PLAN more: after 'spy' on the same machine while it is warm, with the same WORK: the
#   target in one process (`amigo run` on the level-2 files), a warm fit sampled with
#   native frames (fit_native.spy), and a warm fit and detection again, each timed.
# Each step has its own time limit, so that a slow one leaves the next their share, and
# none runs past $DEADLINE seconds (575: the call's limit is 600).
set -u
DATA=${1:?usage: gpu_lease.sh DATA_DIR [batches|profile|spy|more]}
PLAN=${2:-batches}
case $PLAN in
batches | profile | spy | more) ;;
*)
    echo "gpu_lease.sh: unknown plan '$PLAN' (batches, profile, spy or more)" >&2
    exit 2
    ;;
esac
OUT=${OUT:-$(mktemp -d)}
PY=${PY:-python3}
LOG=$OUT/lease.log
START=$(date +%s)
DEADLINE=${DEADLINE:-575} # seconds after START by which every step has ended

# Microseconds from bash 5's EPOCHREALTIME (its decimal point is the locale's: digits only).
START_US=${EPOCHREALTIME//[!0-9]/}
stamp() {
    # Prefix each line with the seconds since the lease's script began (to 0.1 s).
    local us
    while IFS= read -r line; do
        us=$((${EPOCHREALTIME//[!0-9]/} - START_US))
        printf '%6d.%d %s\n' "$((us / 1000000))" "$((us % 1000000 / 100000))" "$line"
    done
}

step() {
    # step LIMIT_S NAME COMMAND...: run it with a limit, stamped, into the log ($STEPLOG if
    # set: steps run side by side each write their own).
    local limit=$1 name=$2 log=${STEPLOG:-$LOG}
    shift 2
    # No step runs past the lease's deadline: a late one is cut, never the reply.
    local left=$((DEADLINE - ($(date +%s) - START) - 15))
    [ "$left" -lt "$limit" ] && limit=$left
    if [ "$limit" -lt 10 ]; then
        echo "=== $name: skipped, ${left} s left" | stamp | tee -a "$LOG"
        return
    fi
    echo "=== $name (limit ${limit} s)" | stamp | tee -a "$LOG"
    local t0=$SECONDS
    # SIGINT first: py-spy writes its samples on it; anything left is killed 10 s later.
    timeout -s INT -k 10 "$limit" "$@" 2>&1 | stamp >>"$log"
    echo "=== $name: exit ${PIPESTATUS[0]} after $((SECONDS - t0)) s" | stamp | tee -a "$LOG"
}

if [ -d .whl ] && [ -z "${SKIP_INSTALL:-}" ]; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site .whl/*.whl || exit 1
    export PYTHONPATH=$PWD/src:/tmp/site
    SPY=/tmp/site/bin/py-spy
else
    SPY=${SPY:-py-spy}
fi
export PYTHONUNBUFFERED=1
# GNU time's peak resident memory where the image has it; the plain command where not.
TIMEV=()
[ -x /usr/bin/time ] && TIMEV=(/usr/bin/time -v)
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.mem \
    --format=csv >>"$LOG" 2>&1
$PY -c "import jax; print('JAX', jax.__version__, jax.devices())" 2>&1 | stamp | tee -a "$LOG"

if [ "$PLAN" = profile ]; then
    # The training on a fifth of the GPU's memory, beside the commands at JAX's default
    # (three quarters): both preallocate, and together they stay under the card's size.
    STEPLOG=$OUT/train.log XLA_PYTHON_CLIENT_MEM_FRACTION=0.2 step "${TRAIN_LIMIT:-400}" \
        "training epochs" $PY benchmarks/train.py --files "${TRAIN_FILES:-12}" \
        --epochs "${TRAIN_EPOCHS:-6}" &
    STEPLOG=$OUT/profile.log step "${PROFILE_LIMIT:-560}" "cold and warm fit + detect" \
        $PY benchmarks/profile_fit.py --platform any --runs both \
        ${SEED:+--seed-cache "$SEED"} ${REFERENCE:+--reference "$REFERENCE"}
    wait
    echo "lease script done after $(($(date +%s) - START)) s" | tee -a "$LOG"
    exit 0
fi

if [ "$PLAN" = more ] && [ -z "${WORK:-}" ]; then
    echo "gpu_lease.sh: plan 'more' needs WORK, the folder a 'spy' call left on this machine" >&2
    exit 2
fi
if [ "$PLAN" = spy ] || [ "$PLAN" = more ]; then
    # WORK: set it to keep the products and caches for a later call on the same machine.
    WORK=${WORK:-$(mktemp -d)}
    mkdir -p "$WORK"
fi
if [ "$PLAN" = more ]; then
    # After 'spy' on the same (still warm) machine, same WORK: the whole target in one
    # process (amigo run on the level-2 files), a warm fit sampled with native frames (what
    # reading programs from XLA's cache costs inside XLA), and the two commands again.
    D=$DATA
    SCI=("$D"/jw01093012001_0310{2,3,4}_00001_nis_cal.fits)
    CAL=("$D"/jw01093015001_0310{2,3,4}_00001_nis_cal.fits)
    export AMIGO_CACHE_DIR=$WORK/cache
    step "${RUN_LIMIT:-100}" "amigo run, one process" ${TIMEV[@]+"${TIMEV[@]}"} $PY -m amigo run \
        --sci "${SCI[@]}" --cal "${CAL[@]}" --out "$WORK/run" --force
    # Native sampling about doubles the fit's time (35 s -> over 75 s on an H200).
    step "${NATIVE_LIMIT:-150}" "warm fit, native frames" "$SPY" record --idle --native -r 50 \
        -f raw -o "$OUT/fit_native.spy" -- $PY -m amigo fit --sci "${SCI[@]}" --cal "${CAL[@]}" \
        --out "$WORK/fit2" --force
    step "${FIT_LIMIT:-60}" "warm fit" ${TIMEV[@]+"${TIMEV[@]}"} $PY -m amigo fit \
        --sci "${SCI[@]}" --cal "${CAL[@]}" --out "$WORK/fit3" --force
    step "${DETECT_LIMIT:-60}" "warm detect" ${TIMEV[@]+"${TIMEV[@]}"} $PY -m amigo detect \
        "$WORK"/fit3/*_calvis.fits --out "$WORK/fit3/detect" --force
    echo "lease script done after $(($(date +%s) - START)) s" | tee -a "$LOG"
    exit 0
fi
if [ "$PLAN" = spy ]; then
    STEPLOG=$OUT/profile.log step "${PROFILE_LIMIT:-470}" "cold and warm fit + detect, sampled" \
        env SPY="$SPY" $PY benchmarks/profile_fit.py --platform any --runs both --spy "$OUT" \
        --out "$WORK/fit" --cache "$WORK/cache" ${REFERENCE:+--reference "$REFERENCE"}
    for run in "host (compiles)" "host" "gpu"; do
        device=${run%% *}
        [ "$device" = gpu ] && device=default
        step "${DETECT_LIMIT:-60}" "detect, chains on the $run" env AMIGO_CACHE_DIR="$WORK/cache" \
            AMIGO_SAMPLER_DEVICE=$device ${TIMEV[@]+"${TIMEV[@]}"} $PY -m amigo detect \
            "$WORK"/fit/*_calvis.fits --out "$WORK/detect_$device" --force
        cp "$WORK/detect_$device/companions.json" "$OUT/companions_$device.json" 2>/dev/null
    done
    echo "lease script done after $(($(date +%s) - START)) s" | tee -a "$LOG"
    exit 0
fi

SCI=$DATA/jw01093012001_03102_00001_nis_cal.fits
CAL=$DATA/jw01093015001_03102_00001_nis_cal.fits
WORK=$(mktemp -d)

# 1. Batch sizes, each cold then warm in one process (the table the docs quote).
step "${BATCH_LIMIT:-300}" "jacobian batches" $PY benchmarks/jacobian_batch.py --platform any \
    --sci "$SCI" --cal "$CAL" --batches "${BATCHES:-8,256,64}" --out "$WORK/batches"
grep -A8 '| batch |' "$LOG" | sed 's/^ *[0-9]* //' >"$OUT/batch.txt"

# 2. A warm fit in a fresh process (what a user's next target costs), sampled by py-spy.
step "${FIT_LIMIT:-80}" "warm fit, default batch, sampled" "$SPY" record --idle -r 50 -f raw \
    -o "$OUT/fit_warm.spy" -- $PY -m amigo fit --sci "$SCI" --cal "$CAL" \
    --out "$WORK/fit" --force

# 3. The same at the largest batch, unsampled, with its peak memory.
step "${BIG_LIMIT:-70}" "warm fit, batch ${BIG_BATCH:-256}" env AMIGO_JVP_BATCH="${BIG_BATCH:-256}" \
    ${TIMEV[@]+"${TIMEV[@]}"} $PY -m amigo fit --sci "$SCI" --cal "$CAL" --out "$WORK/fit_big" --force

# 4. Detection on the first fit's products: cold, then warm sampled by py-spy.
step "${DETECT_LIMIT:-120}" "cold detect" ${TIMEV[@]+"${TIMEV[@]}"} $PY -m amigo detect \
    "$WORK"/fit/*_calvis.fits --out "$WORK/detect_cold" --force
step "${WARM_DETECT_LIMIT:-100}" "warm detect, sampled" "$SPY" record --idle -r 50 -f raw \
    -o "$OUT/detect_warm.spy" -- $PY -m amigo detect "$WORK"/fit/*_calvis.fits \
    --out "$WORK/detect_warm" --force
echo "lease script done after $(($(date +%s) - START)) s" | tee -a "$LOG"
