#!/usr/bin/env bash
# The GPU column of the benchmarks in one short run (issue 11), sized for a
# 15-minute device lease: every step has its own time limit, the log is written
# as it goes, and what finished is packed into one archive at the end.
#
#   bash benchmarks/gpu.sh OUT_DIR [SCALE [STEP ...]]
#
# SCALE=full (default) for the GPU sizes (the default steps take about 400 s on an H100 or
# H200, after a machine start; each step's limit below leaves room for its slowest row);
# SCALE=smoke runs the same steps at CPU sizes (checks the plumbing here).
# STEPs pick steps by name (default: the first five): throughput, tune, equal, sweep,
# sweep-scalarized, and two more that are not run by default: hessian (`tune.py`'s two
# Hessian variants at 256 runs, about 80 s on an H100) and derivatives (`layouts.py
# --derivatives 4096`: the forward pass, `grad` and `jacfwd` at 4096 runs with the
# engine's program and the array program forced), and ablation (`ablation.py
# --compile-rounds 1`: every pass off in turn, about 490 s on an H200; on its own lease).
# `layouts.py` (about 220 s on the H100) is a second call when time is left. Results:
# OUT_DIR/gpu.log and OUT_DIR/gpu-results.tar.gz (the scripts' <name>-gpu.json / .png).
set -u
out=${1:?usage: gpu.sh OUT_DIR [full|smoke]}
scale=${2:-full}
shift $(($# < 2 ? $# : 2))
steps=" ${*:-throughput tune equal sweep sweep-scalarized} "
here=$(cd "$(dirname "$0")" && pwd)
res=$out/results
mkdir -p "$res"/{tp,tune,sweep,sweep-scalarized,hessian,derivatives,ablation}
log=$out/gpu.log
export PYTHONUNBUFFERED=1 PYTHONPATH=$here/..:${PYTHONPATH:-}
py=${PYTHON:-python3}
if [ "$scale" = full ]; then
  big="2048 1048576"; lim=(200 160 90 100 100 150 540); tb="256 4096"; chunk=65536; q=
  hb=256; db=4096
else
  big="8 64"; lim=(150 120 120 120 120 120 120); tb="4"; chunk=256; q=--quick; hb=4; db=8
fi
step() {  # step KEY LIMIT_S NAME COMMAND...: runs when KEY is among the chosen steps
  local t0=$SECONDS key=$1 lim=$2 name=$3
  shift 3
  case $steps in *" $key "*) ;; *) return ;; esac
  echo "=== $name (limit ${lim}s)" >>"$log"
  timeout -k 5 "$lim" "$@" >>"$log" 2>&1
  echo "=== $name: exit $? after $((SECONDS - t0)) s" >>"$log"
}
{
  date -u
  nvidia-smi -L 2>&1
  $py -c "import jax, diffrax, equinox; print('jax', jax.__version__, jax.devices(), 'diffrax', diffrax.__version__, 'equinox', equinox.__version__)" 2>&1
} >>"$log"
tp="$py $here/throughput.py --repeats 3 $q"
# Throughput, float32 first (issue 11's 1e9 body-steps/s target); the default program, the
# array program forced, LGVI and the diffrax baselines in one process.
step throughput "${lim[0]}" "throughput" $tp --out "$res/tp" --dtypes float32 float64 --sweep-only \
  --methods RKMK4 "RKMK4 array" LGVI "diffrax RK4" "diffrax Tsit5" --batches $big
step tune "${lim[1]}" "tune" $py "$here/tune.py" $q --out "$res/tune" --batches $tb --horizons 1000 \
  --variants "reverse (default)" "reverse, discrete adjoint" "forward mode (jacfwd)"
# The equal-accuracy part joins the sweep's JSON (--equal-only reads it back).
step equal "${lim[2]}" "equal accuracy" $tp --out "$res/tp" --equal-only \
  --calibration "$here/results/throughput.json" \
  --variants "RKMK4 default" "RKMK4-cayley scalarized" "RKMKTsit5-cayley scalarized"
step sweep "${lim[3]}" "gain sweep" $py "$here/sweep.py" --out "$res/sweep" --chunk-size $chunk $q
# The same sweep forced scalarized (`sweep(..., scalarize=True)`): on a GPU `sweep` runs
# the array program (a first sweep, compile included, takes less time that way; a compiled
# one more: `so3jax._engine.SWEEP_SCALARIZE`); this keeps both columns measured.
step sweep-scalarized "${lim[3]}" "gain sweep, scalarized program" $py "$here/sweep.py" \
  --out "$res/sweep-scalarized" --chunk-size $chunk --scalarized $q
step hessian "${lim[4]}" "Hessian" $py "$here/tune.py" $q --out "$res/hessian" --batches $hb \
  --horizons 1000 --variants "Hessian (default)" "Hessian, autodiff"
step derivatives "${lim[5]}" "derivatives, engine and array program" $py "$here/layouts.py" $q \
  --repeats 3 --out "$res/derivatives" --derivatives $db
step ablation "${lim[6]}" "ablation" $py "$here/ablation.py" $q --repeats 3 --compile-rounds 1 \
  --out "$res/ablation"
tar -C "$res" -czf "$out/gpu-results.tar.gz" . && rm -rf "$res"
echo "=== done after $SECONDS s" >>"$log"
