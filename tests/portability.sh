#!/usr/bin/env bash
# Developer check (not part of `make test`): the unit tests and nbval under several OpenBLAS
# kernels and with NumPy's SIMD dispatch reduced, so that a reader's CPU gives the same results.
#
#   tests/portability.sh              unit tests + nbval under every configuration
#   tests/portability.sh --unit-only  unit tests only (or SKIP_NBVAL=1)
#
# Prints one summary line per configuration; exits non-zero if any configuration fails.
# OPENBLAS_CORETYPE selects a kernel the CPU must support (SkylakeX needs AVX-512); OpenBLAS
# falls back silently otherwise, so the line also reports the kernel OpenBLAS says it uses.
set -u
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
RUN=(env PYTHONHASHSEED=0 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1)
NBVAL=(--nbval --nbval-current-env --nbval-sanitize-with tests/nbval_sanitize.cfg)
SKIP_NBVAL=${SKIP_NBVAL:-0}
for arg in "$@"; do
  case "$arg" in
    --unit-only) SKIP_NBVAL=1 ;;
    *) echo "usage: $0 [--unit-only]" >&2; exit 2 ;;
  esac
done

# NumPy's runtime-dispatched SIMD targets (NumPy 2.4: X86_V3 = AVX2/FMA3, X86_V4 = AVX-512,
# AVX512_ICL, AVX512_SPR). Naming a feature that is not a dispatch target is an error in some
# NumPy versions and ignored in others, so ask this NumPy which ones it has.
NPY_REDUCED=$("$PY" -c 'from numpy._core._multiarray_umath import __cpu_dispatch__ as d; print(" ".join(d))')

# The kernel OpenBLAS (NumPy's bundled scipy-openblas) reports it uses.
CORENAME='
import ctypes, glob, os, numpy
names = []
for p in glob.glob(os.path.join(os.path.dirname(numpy.__file__), os.pardir, "numpy.libs", "*openblas*")):
    lib = ctypes.CDLL(p)
    for sym in ("scipy_openblas_get_corename64_", "openblas_get_corename64_", "openblas_get_corename"):
        fn = getattr(lib, sym, None)
        if fn is not None:
            fn.restype = ctypes.c_char_p
            names.append(fn().decode())
            break
print(",".join(names) or "?")
'

configs=("OPENBLAS_CORETYPE=Haswell" "OPENBLAS_CORETYPE=Sandybridge" "OPENBLAS_CORETYPE=Zen"
         "OPENBLAS_CORETYPE=SkylakeX" "NPY_DISABLE_CPU_FEATURES=$NPY_REDUCED")
log=$(mktemp -d)
status=0
summary=()
for i in "${!configs[@]}"; do
  cfg=${configs[$i]}
  core=$(env "$cfg" "$PY" -c "$CORENAME" 2>/dev/null || echo "?")
  "${RUN[@]}" "$cfg" "$PY" -m pytest -q -p no:cacheprovider -n 2 --dist loadfile tests --ignore=tests/book >"$log/unit$i.txt" 2>&1
  u=$?
  line="[$cfg] (openblas: $core) unit: $(tail -n 1 "$log/unit$i.txt")"
  [ $u -ne 0 ] && status=1
  if [ "$SKIP_NBVAL" != 1 ]; then
    "${RUN[@]}" "$cfg" "$PY" -m pytest -q -p no:cacheprovider -n 2 --dist loadfile "${NBVAL[@]}" notebooks >"$log/nbval$i.txt" 2>&1
    v=$?
    line="$line | nbval: $(tail -n 1 "$log/nbval$i.txt")"
    [ $v -ne 0 ] && status=1
  fi
  summary+=("$line")
  echo "$line"
done
echo "---- summary (logs in $log)"
printf '%s\n' "${summary[@]}"
[ $status -eq 0 ] && echo "portability: PASS" || echo "portability: FAIL"
exit $status
