#!/usr/bin/env bash
# Run benchmarks/warp_throughput.py on a GPU machine whose Python (3.12) already holds torch and nothing
# of adadex's other dependencies, and that cannot reach a package index.
#
#   bash benchmarks/device/warp_device.sh pack [DATASET [--force]]   # here: wheels for CPython 3.12 into .dev1/ and .dev2/
#   bash benchmarks/device/warp_device.sh install   # there: unpack them into /tmp/site (PYTHONPATH)
#   bash benchmarks/device/warp_device.sh bench OUTDIR   # there: benchmarks/warp_throughput.py's parts, JSON into OUTDIR
#
# Why two folders: warp-lang's wheel is 149 MB (its warp.so holds NVRTC and fat binaries for every GPU
# generation), over the 64 MiB a call may carry. Its warp.so is shipped xz-compressed (81 MB) in three
# pieces over two calls (.dev1 with the other wheels, .dev2 with the rest and a copy of the dataset
# whose human keypoints, unused by the env, are zeroed); warp-clang.so (CPU kernels only) is left out.
# The first call copies .dev1 to /tmp/stage on the machine; the second, on the same warm machine,
# installs everything from /tmp/stage and .dev2. mujoco-studio and PyOpenGL (a viewer's) stay behind.
set -euo pipefail
cd "$(dirname "$0")/../.."
mode=${1:-}
PLAT=(--only-binary=:all: --python-version 3.12 --implementation cp --platform manylinux_2_28_x86_64
      --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64)
WHEELS=(mujoco==4.0.0 mujoco-core==4.0.0 glfw==2.11.0 torchrl==0.14.1 tensordict==0.14.3 pyvers==0.2.3
        gymnasium==1.4.0 farama-notifications==0.0.6 pytorch-kinematics==0.10.0 arm-pytorch-utilities==0.5.0
        pytorch-seed==0.2.0 mujoco-warp==4.0.0 trimesh==5.2.0 manifold3d==3.5.4 orjson==3.13.0 cma==4.5.0)

case "$mode" in
pack)
    dataset=${2:-data/small_pg}
    force=${3:-}
    # .dev1/.dev2 are this script's own output: refuse to write into folders it did not make
    for d in .dev1 .dev2; do
        if [ -e "$d" ] && [ ! -f "$d/.warp_device_pack" ] && [ "$force" != "--force" ]; then
            echo "benchmarks/device/warp_device.sh: error: $d exists and was not written by this script; move it or add --force" >&2
            exit 2
        fi
    done
    [ -d "$dataset/frames" ] || { echo "benchmarks/device/warp_device.sh: error: no dataset at $dataset (adadex data build ...)" >&2; exit 2; }
    rm -rf .dev1 .dev2
    tmp=$(mktemp -d)
    mkdir -p .dev1 .dev2
    touch .dev1/.warp_device_pack .dev2/.warp_device_pack
    grep -qx "/.dev1/" .git/info/exclude 2>/dev/null || printf '/.dev1/\n/.dev2/\n' >> .git/info/exclude
    pip download -q --no-deps "${PLAT[@]}" -d .dev1 "${WHEELS[@]}"
    pip download -q --no-deps "${PLAT[@]}" -d "$tmp" warp-lang==1.19.0
    (cd "$tmp" && mkdir w && cd w && unzip -q ../warp_lang-*.whl && xz -T0 -6 -c warp/bin/warp.so > ../warp.so.xz \
        && rm -rf warp/bin/warp.so warp/bin/warp-clang.so warp/examples warp/tests && tar cJf ../warp_rest.tar.xz .)
    split -b 38000000 "$tmp/warp.so.xz" "$tmp/warpso.part."
    mv "$tmp/warpso.part.aa" .dev1/ && mv "$tmp"/warpso.part.a[b-z] "$tmp/warp_rest.tar.xz" .dev2/
    cp -r "$dataset" "$tmp/small_pg" && python - "$tmp/small_pg/frames/human_keypoints.memmap" <<'PY'
import os, sys
p = sys.argv[1]
if os.path.exists(p):
    with open(p, "r+b") as f:
        f.write(b"\0" * os.path.getsize(p))
PY
    tar cJf .dev2/small_pg_bench.tar.xz -C "$tmp" small_pg
    rm -rf "$tmp"
    du -sh .dev1 .dev2
    ;;
install)
    # Stage 1 (.dev1 carried): the wheels into /tmp/site. Stage 2 (.dev2 carried, same warm machine):
    # warp-lang assembled into /tmp/site, the dataset into /tmp/data.
    mkdir -p /tmp/stage /tmp/site
    for d in .dev1 .dev2; do if [ -d "$d" ]; then cp -n "$d"/* /tmp/stage/; fi; done
    if [ ! -f /tmp/site/.wheels_done ]; then
        python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site /tmp/stage/*.whl
        touch /tmp/site/.wheels_done
    fi
    if [ -f /tmp/stage/warp_rest.tar.xz ] && [ ! -f /tmp/site/warp/bin/warp.so ]; then
        # Python's own tarfile and lzma: the machine may have no xz
        python3 - <<'PY'
import glob, lzma, tarfile
tarfile.open("/tmp/stage/warp_rest.tar.xz").extractall("/tmp/site", filter="data")
tarfile.open("/tmp/stage/small_pg_bench.tar.xz").extractall("/tmp/data", filter="data")
dec = lzma.LZMADecompressor()
with open("/tmp/site/warp/bin/warp.so", "wb") as out:
    for part in sorted(glob.glob("/tmp/stage/warpso.part.*")):
        out.write(dec.decompress(open(part, "rb").read()))
PY
    fi
    ls /tmp/site/warp/bin/warp.so >/dev/null 2>&1 && echo "warp installed; dataset at /tmp/data/small_pg" \
        || echo "wheels installed into /tmp/site; warp-lang comes with .dev2"
    ;;
bench)
    # There, after install: the kernel cache (if .dev3 was staged), then the benchmark parts in order of
    # what the issue's targets need, each process under its own time limit, the JSON into OUTDIR.
    outdir=${2:?usage: bash benchmarks/device/warp_device.sh bench OUTDIR}
    export PYTHONPATH=/tmp/site:. PYTHONUNBUFFERED=1
    for d in .dev3; do if [ -d "$d" ]; then cp -n "$d"/* /tmp/stage/ 2>/dev/null || true; fi; done
    if ls /tmp/stage/warp_kernels_*.tar.xz >/dev/null 2>&1; then python3 benchmarks/device/warp_precompile.py unpack || echo "kernel cache unpack failed: kernels compile on first use"; fi
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
    bench=(python3 benchmarks/warp_throughput.py --dataset /tmp/data/small_pg --force)
    timeout "${ADADEX_BENCH_A:-420}" "${bench[@]}" --parts env,specialist,ppo --batches 4096 --ppo-batches 4096 \
        --budget-s "${ADADEX_BUDGET_A:-330}" --out "$outdir/warp_a.json" || echo "part A ended with $?"
    timeout "${ADADEX_BENCH_B:-120}" "${bench[@]}" --parts sim,physics,collect --batches 4096 --kernel-profile \
        --budget-s 60 --out "$outdir/warp_b.json" || echo "part B ended with $?"
    ADADEX_WARP_TEST_DEVICE=cuda:0 timeout "${ADADEX_TESTS:-100}" python3 -m pytest -q -p no:cacheprovider -x \
        tests/sim/test_warp_backend.py -k "tracking_env or flung or sims_device" 2>&1 | tail -60 || true
    timeout "${ADADEX_BENCH_C:-90}" "${bench[@]}" --parts env --batches 1024,8192 --budget-s 45 \
        --out "$outdir/warp_c.json" || echo "part C ended with $?"
    ;;
*)
    echo "usage: bash benchmarks/device/warp_device.sh pack [DATASET [--force]] | install | bench OUTDIR" >&2
    exit 2
    ;;
esac
