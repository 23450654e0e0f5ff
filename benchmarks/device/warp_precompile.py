"""Build, here on the CPU, the sm_90 CUDA binaries MuJoCo Warp's kernels need on an H100, and unpack them there.

Why: on a lent H100 (compute capability 9.0) ``benchmarks/warp_throughput.py`` spent 277 s of a short
device budget compiling MuJoCo Warp's CUDA kernels with NVRTC on first use. NVRTC ships inside ``warp.so``
and needs no GPU, so the same CUBINs are compiled here ahead of time (about 6 minutes on 2 cores) and
shipped in Warp's kernel-cache layout; on the GPU, ``Module.load`` finds them and compiles nothing.

What ``build`` does (the default command):

1. runs the benchmark's own workload (``warp_throughput.main``, in this process) on Warp's CPU device at
   a small size (B = 256: the sim part then holds every reference's object, as on the GPU; ppo and
   specialist at B = 64 and 4,096 frames), then the pytest selection that ``warp_device.sh bench`` runs
   on the GPU, so that every Warp module they create is created and loaded with the same live kernels;
2. watches every module load (``Module.load``, ``wp.launch``/``launch_tiled`` and
   ``get_suggested_block_size`` are wrapped): for each it works out the ``block_dim`` the same load has on
   a CUDA device (the launch's requested ``block_dim``, else Warp's CUDA default 256; a
   ``get_suggested_block_size`` call — on CUDA only, for MuJoCo Warp's CCD kernels — loads the module's
   default) and compiles that variant right then for ``sm_90`` as CUBIN (``Module._compile(None,
   output_arch=90, use_ptx=False, options=<the variant's resolved options>)``: what
   ``compile_aot_module`` does, for any ``block_dim``) into a work folder laid out like Warp's kernel
   cache, ``<module identifier>/<module identifier>.sm90.cubin`` and ``….meta`` (kept between builds:
   a rebuild compiles only modules whose hash changed);
3. the broadphase kernels compile B in (``worldid % n`` for per-world model arrays): for each one seen
   it makes the same factory's kernel for every ``--gpu-batches`` B and compiles those too;
4. packs the CUBINs and ``.meta`` files, with a manifest, as ``.dev3/warp_kernels_sm90.tar.xz``.

``unpack`` (the GPU machine; standard library and ``warp`` only) extracts the archive into
``warp.config.kernel_cache_dir`` as ``wp.init()`` resolves it there (``~/.cache/warp/1.19.0``, or
``$WARP_CACHE_PATH/1.19.0``): the benchmark process must resolve the same folder (same ``HOME``,
``XDG_CACHE_HOME``, ``WARP_CACHE_PATH``). It loads these files when it compiles for sm_90 as CUBIN:
Warp's automatic choice on a driver older than its toolkit (Warp 1.19.0 is built with CUDA 13.4; driver
580 is CUDA 13.0), or ``warp.config.cuda_output = "cubin"``, which ``exec`` sets before running a script
(a driver of CUDA 13.4 or newer would otherwise make Warp compile PTX, whose files are not here).

``verify`` re-runs the workload in a fresh process and checks, for every load, the file a sm_90 CUBIN load
would open (``Module._get_compile_output_name(None, output_arch=90, use_ptx=False, block_dim=…)`` under an
extracted copy of the archive): hits and misses.

    python benchmarks/device/warp_precompile.py [build] [--batches 256] [--gpu-batches 256,…,16384] [--force]
    python benchmarks/device/warp_precompile.py verify [--batches 1024 --gpu-batches ""]     # a real B, no substitution
    python3 benchmarks/device/warp_precompile.py unpack [--tar FILE] [--cache-dir DIR]        # GPU machine
    python3 benchmarks/device/warp_precompile.py exec benchmarks/warp_throughput.py ARGS…    # GPU machine, CUBIN forced

Limits: the archive matches the code it was built from — rebuild after any change to adadex's sim/env
code, MuJoCo Warp or Warp (a rebuild reuses what did not change). A kernel the GPU run makes that this
run does not (another B than ``--gpu-batches``, other models, a MuJoCo Warp path taken on CUDA only) is
compiled on the GPU as before; ``build`` prints the notes it has about such paths.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import sys
import tarfile
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DEV = ROOT / ".dev3"
TAR_NAME = "warp_kernels_sm90.tar.xz"
MARKER = ".warp_precompile_pack"
MANIFEST = "warp_precompile_manifest.json"
PROG = "benchmarks/device/warp_precompile.py"
DEFAULT_WORK = ROOT / "build" / "warp_precompile_sm90"
#: Warp's block_dim for a CUDA launch that names none (``_resolve_launch_block_dim``)
CUDA_DEFAULT_BLOCK_DIM = 256
MAX_TAR_BYTES = 30 * 1024 * 1024
#: the B a GPU run may use (warp_throughput's --batches, --ppo-batches, --specialist-batch)
GPU_BATCHES = "256,512,1024,2048,4096,8192,16384"
#: mujoco_warp collision_driver factories whose kernels compile in the first dimension of per-world
#: (batched) model arrays, i.e. B
B_SHAPED_FACTORIES = ("_nxn_broadphase", "_sap_broadphase", "_sap_project")


def _die(msg: str, code: int = 2):
    print(f"{PROG}: error: {msg}", file=sys.stderr)
    raise SystemExit(code)


# ------------------------------------------------------------------------------------------------------
# watching module loads

_UNSET = object()


class LoadWatcher:
    """Wraps Warp's launch functions and ``Module.load`` so that every module load on the CPU device calls
    ``on_load(module, cuda_block_dim, kernel, why)`` with the block_dim a CUDA load would use."""

    def __init__(self, on_load, gpu_batches=()):
        self.on_load = on_load
        self.tls = threading.local()
        self.part = "-"
        self.cpu_batch = None    # B of the part running now (set by run_workload)
        self.gpu_batches = tuple(gpu_batches)
        self.variants = {}       # CPU kernel's module -> [(GPU B, same factory's kernel at that B)]
        self.b_shaped = []       # the B-shaped factory calls seen (for the manifest)
        self.b_shaped_modules = set()
        self._undo = []
        self.notes = []          # things seen that the CPU run cannot stand in for

    # --- the CUDA block_dim a launch would use -----------------------------------------------------
    def cuda_block_dim(self, module, kernel, requested):
        key = getattr(kernel, "key", "") or ""
        if "_solve_LD_sparse_fused" in key:
            # mujoco_warp smooth.py: ``dim_block = m.block_dim.solve_LD_sparse_fused if is_cuda else 1``
            from mujoco_warp._src import types

            return types.BlockDim.solve_LD_sparse_fused
        if "_JTDACJ_sparse" in key and requested == 1:
            # solver.py: elliptic cones use threads_per_group=1 on the CPU only: another kernel on CUDA
            self.notes.append(f"{key}: elliptic JTDAJ kernel differs on CUDA (threads_per_group); not covered")
        if requested is _UNSET:
            return module.options["block_dim"]
        if requested is None or requested <= 0:
            return CUDA_DEFAULT_BLOCK_DIM
        return int(requested)

    # --- wrappers ----------------------------------------------------------------------------------
    def _patch(self, obj, name, new):
        old = getattr(obj, name)
        setattr(obj, name, new)
        self._undo.append((obj, name, old))

    def install(self):
        import warp
        import warp._src.context as ctx

        watcher = self
        tls = self.tls
        orig_load = ctx.Module.load

        def wrap_launch(orig, tiled):
            def launch(*args, **kwargs):
                if getattr(tls, "requested", _UNSET) is not _UNSET:     # nested (launch_tiled -> launch)
                    return orig(*args, **kwargs)
                kernel = args[0] if args else kwargs.get("kernel")
                if "block_dim" in kwargs:
                    req = kwargs["block_dim"]
                elif not tiled and len(args) > 12:
                    req = args[12]
                else:
                    req = None
                tls.requested, tls.kernel = req, kernel
                try:
                    return orig(*args, **kwargs)
                finally:
                    tls.requested, tls.kernel = _UNSET, None
            launch.__wrapped__ = orig
            return launch

        def load(module, device, block_dim=None, *args, **kwargs):
            exec_ = orig_load(module, device, block_dim, *args, **kwargs)
            dev = ctx.runtime.get_device(device)
            if dev.is_cpu and not args and not kwargs:
                req = getattr(tls, "requested", _UNSET)
                kernel = getattr(tls, "kernel", None)
                bd = watcher.cuda_block_dim(module, kernel, req)
                watcher.notify(module, bd, kernel, "launch" if req is not _UNSET else "load")
            return exec_

        orig_sugg = ctx.get_suggested_block_size

        def suggested(kernel, device=None):
            # on CUDA this loads the kernel's module at its default block_dim; on the CPU it returns (1, 1)
            watcher.notify(kernel.module, kernel.module.options["block_dim"], kernel, "get_suggested_block_size")
            return orig_sugg(kernel, device)

        new_launch, new_tiled = wrap_launch(ctx.launch, False), wrap_launch(ctx.launch_tiled, True)
        for obj in (warp, ctx):
            self._patch(obj, "launch", new_launch)
            self._patch(obj, "launch_tiled", new_tiled)
            self._patch(obj, "get_suggested_block_size", suggested)
        self._patch(ctx.Module, "load", load)

        # collision_convex.py asks for the CCD kernel's suggested block size on CUDA only
        from mujoco_warp._src import collision_convex as cc

        if hasattr(cc, "_ccd_grid_size"):
            orig_grid = cc._ccd_grid_size

            def ccd_grid_size(kernel, *args, **kwargs):
                watcher.notify(kernel.module, kernel.module.options["block_dim"], kernel, "ccd_grid_size")
                return orig_grid(kernel, *args, **kwargs)

            self._patch(cc, "_ccd_grid_size", ccd_grid_size)

        # kernels specialised on B: the broadphase factories take the first dimension of model arrays that
        # are batched per world (1 or nworld: ``worldid % n`` is compiled in); make the same kernels for the
        # GPU's B too (the CPU run cannot afford B = 8,192)
        from mujoco_warp._src import collision_driver as cd

        for name in B_SHAPED_FACTORIES:
            if hasattr(cd, name):
                self._patch(cd, name, self._b_variants(getattr(cd, name)))
        return self

    def _b_variants(self, factory):
        import inspect

        sig = inspect.signature(factory)
        watcher = self

        def make(*args, **kwargs):
            kernel = factory(*args, **kwargs)
            B = watcher.cpu_batch
            if B is None or B <= 1 or not watcher.gpu_batches:
                return kernel
            bound = sig.bind(*args, **kwargs)
            shaped = [k for k, v in bound.arguments.items()
                      if k.startswith(("ngeom_", "npair_")) and type(v) is int and v == B]
            if not shaped:
                return kernel
            seen = f"{factory.__name__}{tuple(bound.arguments.values())} at B={B} ({watcher.part})"
            if seen not in watcher.b_shaped:
                watcher.b_shaped.append(seen)
            watcher.b_shaped_modules.add(kernel.module)
            out = watcher.variants.setdefault(kernel.module, [])
            for gB in watcher.gpu_batches:
                if gB == B or any(g == gB for g, _ in out):
                    continue
                b2 = sig.bind(*args, **kwargs)
                for k in shaped:
                    b2.arguments[k] = gB
                out.append((gB, factory(*b2.args, **b2.kwargs)))
            return kernel

        make.__wrapped__ = factory
        return make

    def notify(self, module, bd, kernel, why):
        if module not in self.b_shaped_modules or self.cpu_batch in self.gpu_batches:
            self.on_load(module, bd, kernel, why)       # (a kernel made for a B the GPU never runs is not)
        for gB, k in self.variants.get(module, ()):
            self.on_load(k.module, bd, k, f"{why}, B={gB} variant")

    def uninstall(self):
        for obj, name, old in reversed(self._undo):
            setattr(obj, name, old)
        self._undo.clear()


def cuda_artifact(module, block_dim: int, arch: int) -> tuple[str, str, str]:
    """(module dir name, binary file name, meta file name) a CUDA load of ``module`` at ``block_dim`` on an
    ``sm_<arch>`` device with ``warp.config.cuda_output = "cubin"`` opens under the kernel cache
    (``Module.load``: ``_get_compile_output_name(device, block_dim=…)`` under
    ``kernel_cache_dir/get_module_identifier(block_dim)``; the arch suffix is ``warp.config.cuda_arch_suffix``)."""
    from warp._src.context import _validate_cuda_arch_suffix, runtime

    suffix = _validate_cuda_arch_suffix(arch, device_arch=arch, toolkit_version=runtime.toolkit_version)
    ident = module.get_module_identifier(block_dim)
    name = module._get_compile_output_name(None, output_arch=arch, arch_suffix=suffix, use_ptx=False,
                                           block_dim=block_dim)
    return ident, name, module._get_meta_name(block_dim=block_dim)


# ------------------------------------------------------------------------------------------------------
# the workload


def run_workload(a, watcher: LoadWatcher) -> dict:
    """``warp_throughput.main`` on Warp's CPU device, in this process, under ``watcher``."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import warp_throughput as wt

    import inspect

    for name in ("physics_fps", "sim_fps", "env_fps", "collect_fps", "ppo_fps"):
        fn = getattr(wt, name)

        def part(*args, _fn=fn, _name=name, **kwargs):
            B = inspect.signature(_fn).bind(*args, **kwargs).arguments["B"]
            watcher.part, watcher.cpu_batch = f"{_name.removesuffix('_fps')} B={B}", int(B)
            try:
                return _fn(*args, **kwargs)
            finally:
                watcher.cpu_batch = None

        setattr(wt, name, part)
    known = getattr(wt, "PARTS", ())
    parts = [x for x in a.parts.split(",") if x]
    missing = [x for x in parts if x not in known]
    if missing:
        print(f"[workload] parts {missing} are not in this warp_throughput.py ({known}): skipped", flush=True)
        parts = [x for x in parts if x in known]
    with tempfile.TemporaryDirectory() as tmp:
        argv = ["--device", "cpu", "--batches", a.batches, "--steps", str(a.steps), "--parts", ",".join(parts),
                "--ppo-batches", a.ppo_batches, "--out", str(Path(tmp) / "warp_throughput.json"), "--force",
                "--dataset", str(a.dataset)]
        if "specialist" in parts:      # a whole (short) training run: 2 batches of B x 32 frames
            B = _ints(a.ppo_batches)[0]
            argv += ["--specialist-batch", str(B), "--specialist-frames", str(2 * 32 * B)]
        print(f"[workload] warp_throughput.py {' '.join(argv)}", flush=True)
        t0 = time.perf_counter()
        result = wt.main(argv)
    errors = {f"{p}/{b}": r["error"] for p, rows in result["parts"].items() for b, r in rows.items() if "error" in r}
    if errors:
        _die(f"the workload failed, so its modules are incomplete: {errors}")
    return {"workload_s": time.perf_counter() - t0}


#: the GPU-side test selection of ``benchmarks/device/warp_device.sh bench`` (run there with
#: ADADEX_WARP_TEST_DEVICE=cuda:0): its kernels (tiny dataset, B = 2 and 3, model patches) are others
TESTS = ["tests/sim/test_warp_backend.py", "-k", "tracking_env or flung or sims_device"]


def run_tests(a, watcher: LoadWatcher) -> dict:
    """The GPU run's pytest selection, in this process on Warp's CPU device, under ``watcher``."""
    import pytest

    watcher.part, watcher.cpu_batch = "tests", None
    # -n 0: pyproject's addopts hand tests to xdist workers (other processes, unwatched)
    args = ["-q", "-p", "no:cacheprovider", "-x", "-n", "0", "--rootdir", str(ROOT), str(ROOT / TESTS[0]), *TESTS[1:]]
    if a.tests_k:
        args[-1] = a.tests_k
    print(f"[tests] pytest {' '.join(args)}", flush=True)
    env_before = os.environ.get("ADADEX_WARP_TEST_DEVICE")
    os.environ["ADADEX_WARP_TEST_DEVICE"] = "cpu"
    t0 = time.perf_counter()
    cwd = os.getcwd()
    try:
        os.chdir(ROOT)
        code = pytest.main(args)
    finally:
        os.chdir(cwd)
        if env_before is None:
            os.environ.pop("ADADEX_WARP_TEST_DEVICE", None)
        else:
            os.environ["ADADEX_WARP_TEST_DEVICE"] = env_before
    if int(code) != 0:
        print(f"{PROG}: warning: the tests exited with {int(code)}; their modules may be incomplete", file=sys.stderr)
    return {"tests_s": time.perf_counter() - t0, "tests_exit": int(code)}


def _workload_args(p):
    p.add_argument("--dataset", type=Path, default=ROOT / "data" / "small_pg")
    p.add_argument("--batches", default="256", help="B of the physics/sim/env/collect parts on the CPU "
                   "(default 256: the sim part then holds every reference's object, as on the GPU)")
    p.add_argument("--steps", type=int, default=2)
    p.add_argument("--parts", default="physics,sim,env,collect,ppo,specialist",
                   help="warp_throughput parts to run (those the file lacks are skipped)")
    p.add_argument("--ppo-batches", default="64", help="B of the ppo and specialist parts on the CPU")
    p.add_argument("--arch", type=int, default=90, help="CUDA arch to compile for (90: H100)")
    p.add_argument("--no-tests", dest="tests", action="store_false",
                   help="skip the pytest selection the GPU run also runs (tests/sim/test_warp_backend.py -k ...)")
    p.add_argument("--tests-k", default=None, help=f"pytest -k expression (default {TESTS[-1]!r})")
    p.add_argument("--gpu-batches", default=GPU_BATCHES,
                   help="B the GPU run may use (warp_throughput --batches and --ppo-batches together): the "
                        "broadphase kernels, which compile B in, are made for each (default %(default)s)")


def _ints(s: str) -> list[int]:
    try:
        return [int(x) for x in s.split(",") if x.strip()]
    except ValueError:
        _die(f"not a comma-separated list of integers: {s!r}")


def _check_dataset(a):
    if not (Path(a.dataset) / "frames").is_dir():
        _die(f"no dataset at {a.dataset} (build it with adadex data build …)")


def _setup_warp():
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    if wp.config.cuda_arch_suffix is not None:
        _die(f"warp.config.cuda_arch_suffix is {wp.config.cuda_arch_suffix!r}; the GPU run uses None")
    return wp


# ------------------------------------------------------------------------------------------------------
# build


def _owned_or_refuse(path: Path, force: bool):
    if path.exists() and not (path / MARKER).exists() and not force:
        _die(f"{path} exists and was not written by this script; move it or add --force")


def cmd_build(a):
    _check_dataset(a)
    _owned_or_refuse(DEV, a.force)
    work = Path(a.work)
    if work.exists() and not (work / MARKER).exists() and any(work.iterdir()) and not a.force:
        _die(f"work folder {work} exists and was not made by this script; move it or add --force")
    if a.fresh and work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    (work / MARKER).touch()
    wp = _setup_warp()
    compiled, seen = {}, {}
    times = {"compile_s": 0.0, "compiled": 0, "reused": 0}

    def on_load(module, bd, kernel, why):
        ident, name, meta = cuda_artifact(module, bd, a.arch)
        if ident in seen:
            return
        module.get_module_hash(bd)                     # fills resolved_options[bd], as Module.load does
        options = module.resolved_options[bd]
        seen[ident] = {"module": module.name, "block_dim": bd, "binary": f"{ident}/{name}", "meta": f"{ident}/{meta}",
                       "part": watcher.part, "why": why, "kernel": getattr(kernel, "key", None)}
        t0 = time.perf_counter()
        try:
            did = module._compile(None, str(work / ident), name, output_arch=a.arch, use_ptx=False, options=options)
        except Exception as e:                  # noqa: BLE001 — recorded, the others still compile
            seen[ident]["error"] = f"{type(e).__name__}: {e}"[:300]
            print(f"[aot] FAILED {ident} (block_dim={bd}): {e}", flush=True)
            return
        dt = time.perf_counter() - t0
        seen[ident]["compile_s"] = round(dt, 2) if did else 0.0
        times["compile_s"] += dt if did else 0.0
        times["compiled" if did else "reused"] += 1
        compiled[ident] = seen[ident]
        print(f"[aot] {'compiled' if did else 'cached  '} {ident}  block_dim={bd}  ({dt:.1f} s, {watcher.part})",
              flush=True)

    watcher = LoadWatcher(on_load, _ints(a.gpu_batches)).install()
    t0 = time.perf_counter()
    try:
        info = run_workload(a, watcher)
        if a.tests:
            info.update(run_tests(a, watcher))
    finally:
        watcher.uninstall()
    info["total_s"] = time.perf_counter() - t0
    failed = {k: v for k, v in seen.items() if "error" in v}
    # prune work-folder entries this run did not need (a module that changed since an earlier build)
    wanted = set(compiled)
    for d in work.iterdir():
        if d.is_dir() and d.name not in wanted:
            shutil.rmtree(d)
    manifest = {"warp": wp.__version__, "arch": a.arch, "cuda_output": "cubin",
                "mujoco_warp": _version("mujoco_warp"), "python_built_with": sys.version.split()[0],
                "workload": {k: getattr(a, k) for k in ("batches", "steps", "parts", "ppo_batches")},
                "workload_dataset": str(a.dataset), "modules": compiled, "failed": failed,
                "notes": sorted(set(watcher.notes)), "b_shaped_factory_calls": watcher.b_shaped,
                "gpu_batches": _ints(a.gpu_batches), "timing": {**times, **info}}
    if a.no_pack:
        print(json.dumps({k: manifest[k] for k in ("timing", "notes")}, indent=1))
        return 0
    tar_path, raw, packed = pack(work, manifest, a.force)
    print(f"modules: {len(compiled)} ({times['compiled']} compiled now, {times['reused']} from the work folder)"
          f"; failed: {len(failed)}")
    print(f"AOT compile time: {times['compile_s']:.0f} s (workload incl. compile {info['total_s']:.0f} s)")
    print(f"binaries+meta: {raw / 1e6:.1f} MB; {tar_path.relative_to(ROOT)}: {packed / 1e6:.2f} MB")
    for n in manifest["notes"]:
        print(f"note: {n}")
    if failed:
        for k, v in failed.items():
            print(f"failed: {k}: {v['error']}")
    return 1 if failed else 0


def _version(name):
    try:
        from importlib.metadata import version

        return version(name.replace("_", "-"))
    except Exception:       # noqa: BLE001
        return None


def pack(work: Path, manifest: dict, force: bool) -> tuple[Path, int, int]:
    """CUBINs and .meta of ``manifest['modules']`` into ``.dev3/warp_kernels_sm90.tar.xz``."""
    _owned_or_refuse(DEV, force)
    DEV.mkdir(exist_ok=True)
    (DEV / MARKER).touch()
    exclude = ROOT / ".git" / "info" / "exclude"
    if exclude.parent.is_dir():
        lines = exclude.read_text().splitlines() if exclude.exists() else []
        if "/.dev3/" not in lines:
            with open(exclude, "a") as f:
                f.write(("" if not lines or exclude.read_text().endswith("\n") else "\n") + "/.dev3/\n")
    tar_path = DEV / TAR_NAME
    tmp = tar_path.with_suffix(".tmp")
    raw = 0
    with tarfile.open(tmp, "w:xz", preset=9) as tar:
        data = json.dumps(manifest, indent=1, sort_keys=True).encode()
        ti = tarfile.TarInfo(MANIFEST)
        ti.size, ti.mtime = len(data), int(time.time())
        tar.addfile(ti, io.BytesIO(data))
        for ident, m in sorted(manifest["modules"].items()):
            for rel in (m["binary"], m["meta"]):
                f = work / rel
                if not f.is_file():
                    _die(f"{f} missing after the compile")
                raw += f.stat().st_size
                tar.add(f, arcname=rel, recursive=False)
    os.replace(tmp, tar_path)
    size = tar_path.stat().st_size
    if size > MAX_TAR_BYTES:
        print(f"{PROG}: warning: {tar_path} is {size / 1e6:.1f} MB, over the 30 MB budget", file=sys.stderr)
    return tar_path, raw, size


# ------------------------------------------------------------------------------------------------------
# unpack (GPU machine: standard library and warp only)


def _read_manifest(tar: tarfile.TarFile) -> dict:
    try:
        return json.load(tar.extractfile(MANIFEST))
    except KeyError:
        _die(f"{tar.name} holds no {MANIFEST}: not an archive of this script")


def extract(tar_path: Path, dest: Path) -> dict:
    """Extract the module folders of ``tar_path`` into ``dest`` (a kernel cache root); the manifest stays out."""
    with tarfile.open(tar_path, "r:xz") as tar:
        manifest = _read_manifest(tar)
        members = [m for m in tar.getmembers() if m.name != MANIFEST]
        bad = [m.name for m in members if not (m.isfile() and m.name.startswith("wp_") and m.name.count("/") == 1
                                               and ".." not in m.name)]
        if bad:
            _die(f"{tar_path}: unexpected members {bad[:5]}")
        dest.mkdir(parents=True, exist_ok=True)
        kw = {"filter": "data"} if hasattr(tarfile, "data_filter") else {}
        tar.extractall(dest, members=members, **kw)
    return manifest


#: where ``unpack`` looks for the archive when --tar is not given: the carried .dev3, or where
#: ``benchmarks/device/warp_device.sh`` stages carried folders between calls
TAR_CANDIDATES = (DEV / TAR_NAME, Path("/tmp/stage") / TAR_NAME)


def cmd_unpack(a):
    if a.tar is None:
        found = [p for p in TAR_CANDIDATES if p.is_file()]
        if not found:
            _die(f"no archive at {' or '.join(map(str, TAR_CANDIDATES))} (carry .dev3 to this machine)")
        tar_path = found[0]
    else:
        tar_path = Path(a.tar)
        if not tar_path.is_file():
            _die(f"no archive at {tar_path}")
    try:
        import warp as wp
    except ImportError:
        _die("needs warp importable (PYTHONPATH=/tmp/site after benchmarks/device/warp_device.sh install)")
    wp.config.log_level = wp.LOG_WARNING
    if a.cache_dir:
        dest = Path(a.cache_dir)
    else:
        wp.init()
        dest = Path(wp.config.kernel_cache_dir)
    with tarfile.open(tar_path, "r:xz") as tar:
        manifest = _read_manifest(tar)
    if manifest["warp"] != wp.__version__:
        # not an error: Warp just compiles as it would have (and a benchmark script calling this goes on)
        print(f"{PROG}: warning: archive built with warp {manifest['warp']}, this is warp {wp.__version__}: "
              "its files would never be looked up; nothing unpacked", file=sys.stderr)
        return 0
    t0 = time.perf_counter()
    extract(tar_path, dest)
    n = len(manifest["modules"])
    print(f"unpacked {n} sm_{manifest['arch']} CUBIN modules from {tar_path} into {dest} "
          f"({time.perf_counter() - t0:.1f} s)")
    if a.check:
        try:
            _check_loads(wp, dest, manifest)
        except Exception as e:  # noqa: BLE001 — the files stay; Warp reports a bad one when it loads it
            print(f"{PROG}: warning: test-loading the CUBINs failed ({type(e).__name__}: {e})", file=sys.stderr)
    fmt = _gpu_output_format(wp)
    if fmt not in (None, "cubin"):
        print(f"{PROG}: warning: Warp would load {fmt.upper()} on this GPU, not these CUBINs: run the benchmark "
              f'with warp.config.cuda_output = "cubin" ({PROG} exec SCRIPT ARGS… does)', file=sys.stderr)
    return 0


def _check_loads(wp, dest: Path, manifest: dict) -> None:
    """Load (and unload) every unpacked CUBIN on cuda:0: Warp does not recompile a cached binary that fails
    to load, it fails the launch, so one that does not load here is deleted (Warp then compiles that module)."""
    try:
        if not wp.is_cuda_available():
            print("no CUDA device here: the CUBINs were not test-loaded")
            return
        dev = wp.get_device("cuda:0")
    except Exception as e:  # noqa: BLE001
        print(f"{PROG}: warning: no CUDA device to test-load on ({e})", file=sys.stderr)
        return
    if dev.arch != manifest["arch"]:
        print(f"{PROG}: warning: {dev.name} is sm_{dev.arch}; these sm_{manifest['arch']} files are never looked up "
              "there", file=sys.stderr)
        return
    from warp._src.build import load_cuda
    from warp._src.context import runtime

    t0 = time.perf_counter()
    bad = []
    for ident, m in manifest["modules"].items():
        path = dest / m["binary"]
        handle = load_cuda(str(path), dev)
        if handle:
            runtime.core.wp_cuda_unload_module(dev.context, handle)
        else:
            bad.append(ident)
            path.unlink(missing_ok=True)
    print(f"test-loaded {len(manifest['modules']) - len(bad)} of {len(manifest['modules'])} CUBINs on {dev} "
          f"({dev.name}, {time.perf_counter() - t0:.1f} s)")
    if bad:
        print(f"{PROG}: warning: {len(bad)} did not load and were deleted (Warp compiles them): {bad[:5]}",
              file=sys.stderr)


def _gpu_output_format(wp):
    """What Warp's automatic choice loads on cuda:0 here (None without a GPU or when not initialized)."""
    try:
        if not wp.is_cuda_available():
            return None
        return wp.get_device("cuda:0").get_cuda_output_format()
    except Exception:       # noqa: BLE001 — advisory only
        return None


def cmd_exec(a):
    """Run a script (e.g. benchmarks/warp_throughput.py) with ``warp.config.cuda_output = "cubin"`` set first."""
    import runpy

    import warp

    warp.config.cuda_output = "cubin"
    script = Path(a.script)
    if not script.is_file():
        _die(f"no script {script}")
    sys.argv = [str(script), *a.args]
    sys.path.insert(0, str(script.resolve().parent))
    runpy.run_path(str(script), run_name="__main__")
    return 0


# ------------------------------------------------------------------------------------------------------
# verify (here: a fresh process, the workload again, every load's sm_90 path checked in an extracted copy)


def cmd_verify(a):
    _check_dataset(a)
    tar_path = Path(a.tar)
    if a.dir is None and not tar_path.is_file():
        _die(f"no archive at {tar_path}; run build first")
    with tempfile.TemporaryDirectory() as tmp:
        if a.dir is not None:           # a build's work folder (or any kernel cache) instead of the archive
            cache = Path(a.dir)
            manifest = {"modules": {d.name: {} for d in cache.iterdir() if d.is_dir()}}
        else:
            cache = Path(tmp) / "cache"
            manifest = extract(tar_path, cache)
        _setup_warp()
        results = {}

        def on_load(module, bd, kernel, why):
            ident, name, meta = cuda_artifact(module, bd, a.arch)
            if ident in results:
                return
            hit = (cache / ident / name).is_file() and (cache / ident / meta).is_file()
            results[ident] = {"hit": hit, "module": module.name, "block_dim": bd, "part": watcher.part, "why": why}

        watcher = LoadWatcher(on_load, _ints(a.gpu_batches)).install()
        try:
            run_workload(a, watcher)
            if a.tests:
                run_tests(a, watcher)
        finally:
            watcher.uninstall()
    hits = [k for k, v in results.items() if v["hit"]]
    misses = {k: v for k, v in results.items() if not v["hit"]}
    unused = sorted(set(manifest["modules"]) - set(results))
    print(f"verify: {len(results)} CUDA loads predicted; {len(hits)} hit, {len(misses)} miss; "
          f"{len(unused)} archive modules not asked for")
    for k, v in misses.items():
        print(f"  miss: {k} (block_dim={v['block_dim']}, {v['part']}, {v['why']})")
    if a.report:
        Path(a.report).write_text(json.dumps({"loads": results, "unused": unused}, indent=1))
    return 1 if misses else 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd")
    b = sub.add_parser("build", help="run the workload on the CPU, compile sm_90 CUBINs, pack .dev3 (default)")
    _workload_args(b)
    b.add_argument("--work", default=str(DEFAULT_WORK), help="where the CUBINs are compiled (kept: a rerun "
                   "compiles only what changed)")
    b.add_argument("--fresh", action="store_true", help="empty the work folder first")
    b.add_argument("--no-pack", action="store_true")
    b.add_argument("--force", action="store_true", help="write .dev3 / the work folder even if not this script's")
    u = sub.add_parser("unpack", help="GPU machine: extract the archive into Warp's kernel cache")
    u.add_argument("--tar", default=None, help="the archive (default: .dev3/%s, else /tmp/stage/%s)"
                   % (TAR_NAME, TAR_NAME))
    u.add_argument("--cache-dir", default=None,
                   help="kernel cache root to extract into (default: warp.config.kernel_cache_dir after wp.init())")
    u.add_argument("--no-check", dest="check", action="store_false",
                   help="do not test-load the CUBINs on cuda:0 (a CUBIN that fails to load is deleted)")
    v = sub.add_parser("verify", help="fresh process: rerun the workload, check each predicted sm_90 path")
    _workload_args(v)
    v.add_argument("--tar", default=str(DEV / TAR_NAME))
    v.add_argument("--report", type=Path, default=None, help="write every predicted load (hit or miss) as JSON")
    v.add_argument("--dir", type=Path, default=None, help="check against this kernel-cache folder, not --tar")
    e = sub.add_parser("exec", help='run SCRIPT ARGS… with warp.config.cuda_output = "cubin" (GPU machine)')
    e.add_argument("script")
    e.add_argument("args", nargs=argparse.REMAINDER)
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] not in ("build", "unpack", "verify", "exec", "-h", "--help"):
        argv = ["build", *argv]
    a = p.parse_args(argv)
    return {"build": cmd_build, "unpack": cmd_unpack, "verify": cmd_verify, "exec": cmd_exec}[a.cmd](a)


if __name__ == "__main__":
    sys.exit(main())
