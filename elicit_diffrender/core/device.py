"""Device selection and the Warp <-> torch bridge (DLPack, no copies)."""

from __future__ import annotations

import contextlib
import functools
import os
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor

import torch
import warp as wp

from .host_reads import on_host

# Set before anything can initialise Warp: the optional kernel cache location.
if os.environ.get("ELICIT_WARP_CACHE"):
    wp.config.kernel_cache_dir = os.environ["ELICIT_WARP_CACHE"]

_INIT_LOCK = threading.Lock()
_WARP_READY = False


def init_warp() -> None:
    """Initialise Warp once (thread-safe); quiet unless ``ELICIT_WARP_VERBOSE`` is set (``elicit --verbose``)."""
    global _WARP_READY
    with _INIT_LOCK:
        if _WARP_READY:
            return
        wp.config.log_level = wp.LOG_INFO if os.environ.get("ELICIT_WARP_VERBOSE") else wp.LOG_WARNING
        if os.environ.get("ELICIT_WARP_VERBOSE"):
            wp.init()
        else:
            with _native_stderr_silenced():
                wp.init()  # its native code prints a no-GPU banner straight to stderr
        _WARP_READY = True


@contextlib.contextmanager
def _native_stderr_silenced() -> Iterator[None]:
    """File descriptor 2 points at /dev/null inside the block (what C code prints there is dropped)."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def default_device() -> torch.device:
    """``cuda`` when torch and Warp both see a GPU, else ``cpu``; ``ELICIT_DEVICE`` overrides."""
    forced = os.environ.get("ELICIT_DEVICE")
    if forced:
        return torch.device(forced)
    init_warp()
    if torch.cuda.is_available() and wp.is_cuda_available():
        return torch.device("cuda")
    return torch.device("cpu")


def warp_device(device: torch.device) -> str:
    """Warp's name for a torch device."""
    if device.type == "cuda":
        return f"cuda:{device.index or 0}"
    return "cpu"


_LOADED: set[tuple[int, str]] = set()


def load_kernel(kernel, device: torch.device) -> None:
    """Compile/load a kernel's module once per device, so parallel launches never race to compile it."""
    key = (id(kernel), warp_device(device))
    if key not in _LOADED:
        init_warp()
        wp.load_module(kernel.module, device=key[1])
        _LOADED.add(key)


def to_warp(tensor: torch.Tensor, dtype=None) -> wp.array:
    """A Warp view of a contiguous tensor (shares memory; never touches ``tensor.grad``)."""
    init_warp()
    t = tensor.detach()
    if not t.is_contiguous():
        raise ValueError("to_warp needs a contiguous tensor; call .contiguous() first")
    return wp.from_torch(t, dtype=dtype, requires_grad=False)


def warp_scalar(dtype: torch.dtype):
    """Warp's scalar type for a torch float dtype (float32 or float64)."""
    if dtype == torch.float32:
        return wp.float32
    if dtype == torch.float64:
        return wp.float64
    raise TypeError(f"only float32 and float64 are supported, got {dtype}")


def host_tensor(tensor: torch.Tensor) -> torch.Tensor:
    """``tensor`` (detached) on the host: itself where it is there already; a tensor on a device is copied, a host
    sync that :func:`~elicit_diffrender.core.host_reads.count_host_reads` counts."""
    with on_host():
        return tensor.detach().cpu()


def host_box(box: torch.Tensor) -> tuple[list[float], list[float]]:
    """A (2, 3) box's corners as Python floats (float64 arithmetic without small-tensor overheads). Boxes are kept
    on the host (``BoxedVolume.box_host``, the observation spaces), so this waits for no device (see
    :func:`host_tensor`)."""
    with on_host():
        lo, hi = host_tensor(box).double().tolist()
    return lo, hi


def grid_frame(grid, box: torch.Tensor, shape: tuple[int, ...]):
    """The ``GridFrame`` struct (of ``grid = grid_funcs(dtype)``) locating a node-aligned grid of
    ``shape`` over ``box`` (2, 3)."""
    lo, hi = host_box(box)
    scale = [(n - 1) / (b - a) for n, a, b in zip(shape, lo, hi, strict=True)]
    return grid.make_frame(lo, scale, tuple(shape))


@functools.cache
def _cgroup_cpu_quota() -> int | None:
    """CPUs allowed by a cgroup v2 quota (``cpu.max``: a container's ``--cpus``, a pod's limit), if any;
    read once (every kernel launch asks)."""
    try:
        quota, period = open("/sys/fs/cgroup/cpu.max").read().split()[:2]
    except (OSError, ValueError):
        return None
    if quota == "max":
        return None
    return max(1, int(int(quota) // int(period)))


def cpus_given() -> int:
    """The CPUs this process is given: its affinity mask (``taskset``), capped by a cgroup quota (a
    container's limit) and by ``OMP_NUM_THREADS`` when set (Ray sets it to a task's ``num_cpus``)."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        n = os.cpu_count() or 1
    omp = os.environ.get("OMP_NUM_THREADS", "").strip()
    caps = [_cgroup_cpu_quota(), int(omp) if omp.isdigit() and int(omp) > 0 else None]
    return max(1, min([n, *(c for c in caps if c is not None)]))


def cpu_threads() -> int:
    """Threads used to split one CPU kernel launch (Warp runs a CPU launch on one thread)."""
    return min(cpus_given(), 8)


def size_thread_pools() -> int:
    """Size torch's intra-op pool and Dr.Jit's (Mitsuba's) pool to :func:`cpus_given`, as the Warp launch
    split already is, so that processes sharing a machine do not oversubscribe its cores; returns it."""
    n = cpus_given()
    torch.set_num_threads(n)
    from .mitsuba_variant import mitsuba

    mitsuba()  # Dr.Jit is imported there, after its LLVM is located
    import drjit as dr

    dr.set_thread_count(n)
    return n


def launch_parts(n_items: int, device: torch.device) -> int:
    """How many pieces :func:`launch` splits ``n_items`` threads into: 1 on CUDA, one per CPU thread."""
    if device.type == "cuda":
        return 1
    return min(cpu_threads(), max(1, n_items // 256))


def launch(
    kernel, n_items: int, device: torch.device, args: Sequence | Callable[[int], Sequence], parts: int | None = None
) -> None:
    """Run ``kernel`` over ``n_items`` threads; its first argument is the first item of the launch.

    On CUDA: one launch on torch's current stream, so Warp and torch work stay in order without a
    sync. On CPU, where one launch runs on one thread: ``parts`` contiguous pieces (default
    :func:`launch_parts`) in parallel threads. ``args`` are the other arguments, or ``args(part)``
    gives each piece its own (per-thread gradient buffers).
    """
    if n_items == 0:
        return
    load_kernel(kernel, device)
    per_part = args if callable(args) else (lambda part: args)
    wdev = warp_device(device)
    if device.type == "cuda":
        stream = wp.stream_from_torch(torch.cuda.current_stream(device))
        wp.launch(kernel, dim=n_items, inputs=[0, *per_part(0)], device=wdev, stream=stream)
        return
    n_parts = launch_parts(n_items, device) if parts is None else parts
    split_launch(n_items, n_parts, lambda b, e, p: wp.launch(kernel, dim=e - b, inputs=[b, *per_part(p)], device=wdev))


_SCRATCH: dict[tuple, torch.Tensor] = {}


def partial_sums(name: str, like: torch.Tensor, parts: int) -> list[torch.Tensor]:
    """One zeroed tensor shaped like ``like`` per launch piece, for partial sums that the caller adds into the
    first and returns. The first is fresh; the others are reused from the last call with the same ``name`` and
    shape (a fresh one pays its page faults on every call: 2 ms for 25 MB here), valid until that next call."""
    bufs = [torch.zeros_like(like, memory_format=torch.contiguous_format)]
    for part in range(1, parts):
        key = (name, part, tuple(like.shape), like.dtype, like.device)
        buf = _SCRATCH.get(key)
        if buf is None:
            buf = _SCRATCH[key] = torch.zeros_like(like, memory_format=torch.contiguous_format)
        else:
            buf.zero_()
        bufs.append(buf)
    return bufs


_POOL: ThreadPoolExecutor | None = None


def _forget_pool() -> None:
    """In a forked child the pool's threads are gone: start a new pool there when one is needed."""
    global _POOL
    _POOL = None


os.register_at_fork(after_in_child=_forget_pool)


def _pool() -> ThreadPoolExecutor:
    """The worker threads that run the pieces of split launches (created once: starting threads per launch cost
    about a millisecond per training step)."""
    global _POOL
    with _INIT_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max_workers=max(1, cpu_threads() - 1), thread_name_prefix="elicit-launch")
    return _POOL


def split_launch(n_items: int, parts: int, run: Callable[[int, int, int], None]) -> None:
    """Call ``run(begin, end, part)`` for ``parts`` contiguous pieces of [0, n_items), in parallel: piece 0 on
    the calling thread, the others on a shared pool of worker threads.

    Warp releases the GIL during a CPU launch, so Python threads give real parallelism.
    """
    if parts <= 1:
        run(0, n_items, 0)
        return
    bounds = [n_items * p // parts for p in range(parts + 1)]
    pending = [_pool().submit(run, bounds[p], bounds[p + 1], p) for p in range(1, parts)]
    error: BaseException | None = None
    try:
        run(bounds[0], bounds[1], 0)
    except BaseException as exc:  # noqa: BLE001 - re-raised once every piece has finished
        error = exc
    for future in pending:
        try:
            future.result()
        except BaseException as exc:  # noqa: BLE001
            error = error or exc
    if error is not None:
        raise error
