#!/usr/bin/env bash
# The CUDA path on one GPU, in one go: the kernel and fit tests on CUDA, the kernel and render benchmarks,
# and a time-boxed `paper`-preset fit of a subject with its evaluation. Every step has its own time limit;
# one that fails or runs out is recorded and the next one runs. Results land in OUT:
#   gpu_check.md / gpu_check.json   the steps, their exit codes and times, the machine
#   kernels_cuda.{json,md}          scripts/bench_kernels.py --device cuda --quick --paper-sizes
#   render_cuda.{json,md}           scripts/bench_render.py --variant cuda_ad_rgb
#   logs.tar.gz                     every step's log, the fit's run.json, metrics and evaluation grids
#
#   scripts/gpu_check.sh OUT SUBJECT [INIT_STEPS,STEPS]   # SUBJECT: an elicit-subject/1 folder (`elicit synth`)
#   ELICIT_DEVICE=cpu TESTS=tests/test_volume.py scripts/gpu_check.sh OUT SUBJECT 5,5   # a dry run on the CPU
#
# Set up first as the README says (scripts/setup.sh); PYTHON names the interpreter (default: .venv/bin/python
# when present, else python3). The tests run beside the benchmarks on their own cores and few threads, so they
# cost no wall time; the benchmarks and the fit run one after another. INIT_STEPS,STEPS: the fit's two stages
# (default 1000,1500: a tenth of the paper's schedule). TESTS: the test files (default: kernels and fit).
set -uo pipefail
cd "$(dirname "$0")/.."
usage() { echo "gpu_check.sh: $1 (usage: scripts/gpu_check.sh OUT SUBJECT [INIT_STEPS,STEPS])" >&2; exit 2; }
[ $# -ge 2 ] || usage "OUT and SUBJECT are required"
OUT=$1 SUBJECT=$2
[ -f "$SUBJECT/subject.json" ] || usage "$SUBJECT: not a subject folder (no subject.json)"
IFS=, read -r INIT_STEPS FIT_STEPS <<<"${3:-1000,1500}"
[[ $INIT_STEPS =~ ^[0-9]+$ && $FIT_STEPS =~ ^[0-9]+$ ]] || usage "${3}: steps must be INIT_STEPS,STEPS (integers)"
PY=${PYTHON:-$([ -x .venv/bin/python ] && echo .venv/bin/python || echo python3)}
mkdir -p "$OUT" && OUT=$(cd "$OUT" && pwd)
WORK=$(mktemp -d) LOGS=$WORK/logs
mkdir -p "$LOGS"
export ELICIT_DEVICE=${ELICIT_DEVICE:-cuda} PYTHONUNBUFFERED=1
TESTS=${TESTS:-tests/test_volume.py tests/test_skinning.py tests/test_fit.py}
if [ "$ELICIT_DEVICE" = cuda ]; then VARIANT=cuda_ad_rgb SIZES=--paper-sizes; else VARIANT=llvm_ad_rgb SIZES=; fi
NCPU=$(nproc)
HALF=$((NCPU / 2 > 0 ? NCPU / 2 : 1))

command -v taskset >/dev/null || taskset() { shift 2; "$@"; }  # no util-linux: no core pinning

step() {  # step NAME LIMIT_S CPUS COMMAND...: run with a time limit on the given cores, log to LOGS/NAME.log
  local name=$1 limit=$2 cpus=$3
  shift 3
  local t0=$EPOCHREALTIME rc secs
  echo "[gpu_check] $name (limit ${limit}s)"
  taskset -c "$cpus" timeout --kill-after=10 "$limit" "$@" >"$LOGS/$name.log" 2>&1
  rc=$?
  secs=$(awk -v a="$t0" -v b="$EPOCHREALTIME" 'BEGIN { printf "%.1f", b - a }')
  echo "[gpu_check] $name: rc $rc in ${secs}s"
  tail -n 5 "$LOGS/$name.log" | sed 's/^/    /'
  echo "{\"step\": \"$name\", \"rc\": $rc, \"seconds\": $secs, \"limit_s\": $limit}" >>"$LOGS/steps.jsonl"
}

# The machine and what each library sees.
export ELICIT_MITSUBA_VARIANT=$VARIANT
step environment 60 "0-$((NCPU - 1))" "$PY" - <<'EOF'
import json, os, platform, subprocess
import torch, warp as wp
from elicit_diffrender.core.mitsuba_variant import mitsuba
wp.init()
mi = mitsuba()  # the variant ELICIT_MITSUBA_VARIANT names
import drjit as dr
info = {
    "device": os.environ["ELICIT_DEVICE"],
    "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None, "python": platform.python_version(), "torch": torch.__version__,
    "torch_cuda": torch.version.cuda, "warp": wp.config.version, "warp_cuda": wp.is_cuda_available(),
    "drjit": dr.__version__, "mitsuba": mi.__version__, "mitsuba_variants": mi.variants(),
}
try:
    info["driver"] = subprocess.run(["nvidia-smi", "--query-gpu=driver_version,memory.total", "--format=csv,noheader"],
                                    capture_output=True, text=True).stdout.strip()
except OSError:
    info["driver"] = None
info["mitsuba_variant"] = mi.variant()
print(json.dumps(info))
EOF

# The tests beside the benchmarks, on the upper half of the cores.
# shellcheck disable=SC2086  # TESTS is a list of files
OMP_NUM_THREADS=2 step tests 420 "$HALF-$((NCPU - 1))" "$PY" -m pytest -q -p no:cacheprovider $TESTS \
  --junitxml="$LOGS/tests.xml" &
TESTS=$!

step bench_kernels 150 "0-$((HALF - 1))" "$PY" scripts/bench_kernels.py --device "$ELICIT_DEVICE" --quick $SIZES \
  --name "kernels_$ELICIT_DEVICE" --out "$OUT"
step bench_render 90 "0-$((HALF - 1))" "$PY" scripts/bench_render.py --variant "$VARIANT" --name "render_$ELICIT_DEVICE" \
  --out "$OUT"
step fit_paper 240 "0-$((HALF - 1))" "$PY" -m elicit_diffrender.apps.cli fit "$SUBJECT" --out "$WORK/fit" --preset paper \
  --set "init_steps=$INIT_STEPS" --set "steps=$FIT_STEPS" --set checkpoint_every=500 --set preview_every=100000
step eval_paper 90 "0-$((HALF - 1))" "$PY" -m elicit_diffrender.apps.cli eval "$WORK/fit" "$SUBJECT" \
  --out "$WORK/fit/metrics.json"
wait "$TESTS"

# The report: steps, machine, test counts, the fit's time and quality.
"$PY" - "$OUT" "$WORK" "$INIT_STEPS" "$FIT_STEPS" <<'EOF'
import json, sys
import xml.etree.ElementTree as ET
from pathlib import Path

out, work, init_steps, fit_steps = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
steps = [json.loads(s) for s in (work / "logs" / "steps.jsonl").read_text().splitlines()]
report = {"steps": steps, "fit_schedule": {"init_steps": init_steps, "steps": fit_steps}}
env_log = (work / "logs" / "environment.log").read_text().strip().splitlines()
report["machine"] = json.loads(env_log[-1]) if env_log and env_log[-1].startswith("{") else None
junit = work / "logs" / "tests.xml"
if junit.is_file():
    suite = ET.parse(junit).getroot()
    suite = suite if suite.tag == "testsuite" else suite[0]
    report["tests"] = {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}
    report["tests"]["failed"] = [
        f"{case.get('classname')}::{case.get('name')}: {(case[0].get('message') or '')[:300]}"
        for case in suite.iter("testcase") if len(case) and case[0].tag in ("failure", "error")
    ]
run = work / "fit" / "run.json"
if run.is_file():
    report["fit_run"] = json.loads(run.read_text())
metrics = work / "fit" / "metrics.json"
if metrics.is_file():
    report["fit_metrics"] = json.loads(metrics.read_text())
(out / "gpu_check.json").write_text(json.dumps(report, indent=2))
m = report["machine"] or {}
lines = [f"# {m.get('device', '?')} check on {m.get('gpu') or 'the CPU'}", "",
         f"Driver {m.get('driver')}, torch {m.get('torch')} (CUDA {m.get('torch_cuda')}), Warp {m.get('warp')}, "
         f"Mitsuba {m.get('mitsuba')}, Dr.Jit {m.get('drjit')}.", "", "| step | exit code | seconds | limit |",
         "|---|---|---|---|"]
lines += [f"| {s['step']} | {s['rc']} | {s['seconds']:.1f} | {s['limit_s']} |" for s in steps]
if "tests" in report:
    t = report["tests"]
    lines += ["", f"Tests on {m.get('device')}: {t['tests']} run, {t['failures']} failed, {t['errors']} errors, {t['skipped']} skipped."]
    lines += [f"- {f}" for f in t["failed"]]
print("\n".join(lines))
(out / "gpu_check.md").write_text("\n".join(lines) + "\n")
EOF
cp "$WORK/fit/run.json" "$WORK/fit/metrics.json" "$WORK/fit/"*.png "$LOGS/" 2>/dev/null  # eval's grids too
tar -czf "$OUT/logs.tar.gz" -C "$WORK" logs
echo "[gpu_check] wrote $OUT"
